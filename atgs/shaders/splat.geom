#version 330 core
// Stage 2 of 2 (after splat.vert): emits the triangle of one Gaussian. It is the equilateral
// triangle around the unit circle of the frame scaled by (h1, h2) along the eigen-axes, so it
// contains the +-h1, +-h2 ellipse (vertices at distance 2); only the ellipse inside it writes
// pixels (splat.frag). A triangle that reaches outside the viewport is replaced by the
// ellipse's bounding box clamped to the viewport (two triangles): llvmpipe's clipping of such
// triangles interpolated v_white wrongly (up to 0.3 in sigma, found against the training
// rasterizer), and a box inside the viewport needs no clipping at all.
layout(points) in;
layout(triangle_strip, max_vertices = 4) out;

uniform vec2 u_size;            // width, height in pixels

in vec4 g_axes[];               // h1 e1, h2 e2 (pixels)
in vec2 g_white[];              // h1 / sqrt(l1), h2 / sqrt(l2)
in vec4 g_color[];
flat in int g_keep[];

// Position in the Gaussian's whitened frame (units of standard deviations along the
// eigen-axes); affine over the primitive, so screen-linear interpolation gives every pixel center
// its exact Mahalanobis coordinates: sigma = 0.5 |v_white|^2 = 0.5 d^T Sigma2d^-1 d.
noperspective out vec2 v_white;
flat out vec4 v_color;          // rgb (or view depth), opacity

const vec2 CORNERS[3] = vec2[3](vec2(0.0, 2.0), vec2(-1.7320508, -1.0), vec2(1.7320508, -1.0));

void emit(vec2 pix, vec2 white) {
    gl_Position = vec4(2.0 * pix.x / u_size.x - 1.0, 1.0 - 2.0 * pix.y / u_size.y, 0.0, 1.0);
    v_white = white;
    v_color = g_color[0];
    EmitVertex();
}

void main() {
    if (g_keep[0] == 0) return;
    vec2 center = gl_in[0].gl_Position.xy;
    vec2 a1 = g_axes[0].xy, a2 = g_axes[0].zw;
    vec2 p[3];
    for (int c = 0; c < 3; ++c) p[c] = center + CORNERS[c].x * a1 + CORNERS[c].y * a2;
    vec2 lo = min(p[0], min(p[1], p[2])), hi = max(p[0], max(p[1], p[2]));
    if (all(greaterThanEqual(lo, vec2(0.0))) && all(lessThanEqual(hi, u_size))) {
        for (int c = 0; c < 3; ++c) emit(p[c], CORNERS[c] * g_white[0]);
    } else {
        // the ellipse's own bounding box (tighter than the triangle's), clamped to the viewport
        vec2 ext = sqrt(a1 * a1 + a2 * a2);
        lo = max(center - ext, vec2(0.0));
        hi = min(center + ext, u_size);
        if (any(greaterThanEqual(lo, hi))) return;
        // whitened coordinates of an arbitrary pixel position q (the frame is affine)
        vec2 w1 = a1 * (g_white[0].x / dot(a1, a1)), w2 = a2 * (g_white[0].y / dot(a2, a2));
        vec2 q;
        q = vec2(lo.x, lo.y); emit(q, vec2(dot(q - center, w1), dot(q - center, w2)));
        q = vec2(hi.x, lo.y); emit(q, vec2(dot(q - center, w1), dot(q - center, w2)));
        q = vec2(lo.x, hi.y); emit(q, vec2(dot(q - center, w1), dot(q - center, w2)));
        q = vec2(hi.x, hi.y); emit(q, vec2(dot(q - center, w1), dot(q - center, w2)));
    }
    EndPrimitive();
}
