#version 330 core
// Stage 1 of 2 (the geometry shader splat.geom is stage 2): one invocation per Gaussian.
// The draw is GL_POINTS over an element buffer listing the Gaussians back to front; this
// shader does the EWA projection once per Gaussian and the geometry shader emits its
// triangle. (On llvmpipe the vertex pipeline is single threaded and bounds small splats and
// low resolutions: projecting once per Gaussian instead of once per triangle corner is
// ~20% faster than three vertex invocations, and one indexed draw is about twice as fast as
// instancing.)
// The Gaussians live in an integer texture, 3 texels each:
// (mean.xyz, opacity) | (cov00, cov01, cov02, cov11) | (cov12, cov22, rg16, b16).
// Conventions follow atgs.render (OpenCV camera, pixel centers at +0.5, EWA with 0.3 px^2
// dilation, gsplat's Jacobian clamp, near plane, 3-sigma support).

uniform usampler2D u_data;
uniform int u_per_row;          // Gaussians per texture row
uniform mat4 u_w2c;             // OpenCV world-to-camera
uniform vec4 u_intr;            // fx, fy, cx, cy
uniform vec4 u_lim;             // Jacobian clamp: x/z in [-lim.x, lim.y], y/z in [-lim.z, lim.w]
uniform float u_near;
uniform float u_dilation;
uniform float u_scale2;         // scale modifier squared (covariance scales with its square)
uniform float u_extent;         // splat half-extent in standard deviations (3)
uniform float u_alpha_min;
uniform int u_mode;             // 0 color, 1 depth (the color is replaced by the view depth z)

// To the geometry shader: the splat's half-axes in pixels (h1 e1, h2 e2), the whitened
// length of those axes in standard deviations, color (or view depth z in depth mode, so that
// blending gives the rasterizer's sum z alpha T) and opacity; g_keep = 0 drops the Gaussian
// (behind the near plane, degenerate, or too faint).
out vec4 g_axes;
out vec2 g_white;
out vec4 g_color;
flat out int g_keep;

void cull() {
    g_keep = 0;
    gl_Position = vec4(0.0);
}

void main() {
    int i = gl_VertexID;
    g_keep = 1;
    ivec2 base = ivec2((i % u_per_row) * 3, i / u_per_row);
    uvec4 t0 = texelFetch(u_data, base, 0);
    uvec4 t1 = texelFetch(u_data, base + ivec2(1, 0), 0);
    uvec4 t2 = texelFetch(u_data, base + ivec2(2, 0), 0);
    vec3 mean = uintBitsToFloat(t0.xyz);
    float opacity = uintBitsToFloat(t0.w);
    vec4 c1 = uintBitsToFloat(t1);
    vec2 c2 = uintBitsToFloat(t2.xy);
    mat3 cov3 = mat3(c1.x, c1.y, c1.z,
                     c1.y, c1.w, c2.x,
                     c1.z, c2.x, c2.y) * u_scale2;

    vec4 pc = u_w2c * vec4(mean, 1.0);
    if (pc.z <= u_near || opacity < u_alpha_min) { cull(); return; }

    float fx = u_intr.x, fy = u_intr.y;
    float iz = 1.0 / pc.z;
    float tx = pc.z * clamp(pc.x * iz, -u_lim.x, u_lim.y);
    float ty = pc.z * clamp(pc.y * iz, -u_lim.z, u_lim.w);
    // Rows of J (2x3) times the rotation of the view matrix.
    mat3 Rv = mat3(u_w2c);
    vec3 j0 = vec3(fx * iz, 0.0, -fx * tx * iz * iz);
    vec3 j1 = vec3(0.0, fy * iz, -fy * ty * iz * iz);
    vec3 r0 = j0 * Rv;   // row vector times matrix = (Rv^T j0)^T
    vec3 r1 = j1 * Rv;
    vec3 s0 = cov3 * r0;
    float a = dot(r0, s0) + u_dilation;
    float b = dot(r1, s0);
    float c = dot(r1, cov3 * r1) + u_dilation;
    float det = a * c - b * b;
    if (!(det > 0.0)) { cull(); return; }

    vec2 center = vec2(fx * pc.x * iz + u_intr.z, fy * pc.y * iz + u_intr.w);

    // Eigen-decomposition of Sigma2d: the splat spans +-k sigma along both eigen-axes.
    float mid = 0.5 * (a + c);
    float disc = sqrt(max(mid * mid - det, 0.0));
    float l1 = mid + disc;
    float l2 = max(mid - disc, 1e-6);
    vec2 e1;
    if (abs(b) > 1e-12 * l1) {
        e1 = normalize(vec2(b, l1 - a));
    } else {
        e1 = (a >= c) ? vec2(1.0, 0.0) : vec2(0.0, 1.0);
    }
    vec2 e2 = vec2(-e1.y, e1.x);
    // Beyond sqrt(2 ln(o / alpha_min)) sigmas alpha < alpha_min: a faint Gaussian gets a smaller triangle.
    float k = min(u_extent, sqrt(max(2.0 * log(opacity / u_alpha_min), 0.0)));
    if (k <= 0.0) { cull(); return; }
    // The triangle only has to contain the pixel centers inside the ellipse (the fragment
    // shader cuts the rest): a hair of slack for rounding, no more, since at low resolutions
    // llvmpipe's cost follows the triangle's area (dropping a half-pixel slack: 13% at 160x120).
    float h1 = k * sqrt(l1) * 1.0001 + 0.01, h2 = k * sqrt(l2) * 1.0001 + 0.01;

    gl_Position = vec4(center, 0.0, 1.0);  // pixels; the geometry shader maps to NDC
    g_axes = vec4(h1 * e1, h2 * e2);
    g_white = vec2(h1 * inversesqrt(l1), h2 * inversesqrt(l2));
    vec3 rgb = vec3(float(t2.z & 0xFFFFu), float(t2.z >> 16u), float(t2.w & 0xFFFFu)) / 65535.0;
    g_color = vec4(u_mode == 1 ? vec3(pc.z) : rgb, opacity);
}
