#version 330 core
// Stage 2 of 2 (after splat.vert): emits the triangle of one Gaussian. It is the equilateral
// triangle around the unit circle of the frame scaled by (h1, h2) along the eigen-axes, so it
// contains the +-h1, +-h2 ellipse (vertices at distance 2); only the ellipse inside it writes
// pixels (splat.frag).
layout(points) in;
layout(triangle_strip, max_vertices = 3) out;

uniform vec2 u_size;            // width, height in pixels

in vec4 g_axes[];
in vec2 g_white[];
in vec4 g_color[];
flat in int g_keep[];

// Position in the Gaussian's whitened frame (units of standard deviations along the
// eigen-axes); affine over the triangle, so screen-linear interpolation gives every pixel center
// its exact Mahalanobis coordinates: sigma = 0.5 |v_white|^2 = 0.5 d^T Sigma2d^-1 d.
noperspective out vec2 v_white;
flat out vec4 v_color;          // rgb (or view depth), opacity

const vec2 CORNERS[3] = vec2[3](vec2(0.0, 2.0), vec2(-1.7320508, -1.0), vec2(1.7320508, -1.0));

void main() {
    if (g_keep[0] == 0) return;
    vec2 center = gl_in[0].gl_Position.xy;
    for (int c = 0; c < 3; ++c) {
        vec2 corner = CORNERS[c];
        vec2 pix = center + corner.x * g_axes[0].xy + corner.y * g_axes[0].zw;
        gl_Position = vec4(2.0 * pix.x / u_size.x - 1.0, 1.0 - 2.0 * pix.y / u_size.y, 0.0, 1.0);
        v_white = corner * g_white[0];
        v_color = g_color[0];
        EmitVertex();
    }
    EndPrimitive();
}
