#version 330 core
// Stage 1 of 2 (the geometry shader splat.geom is stage 2): one invocation per Gaussian.
// The draw is GL_POINTS over an element buffer listing the Gaussians back to front; this
// shader does the EWA projection once per Gaussian and the geometry shader emits its
// triangle. (On llvmpipe the vertex pipeline is single threaded and bounds small splats and
// low resolutions: projecting once per Gaussian instead of once per triangle corner is
// ~20% faster than three vertex invocations, and one indexed draw is about twice as fast as
// instancing.)
// The Gaussians are vertex attributes, 40 bytes each in four column buffers (viewer/packing.py):
// mean float32, rotation int16 (32767 q / |q|), scale float32, opacity and rgb uint16 (65535 v);
// the covariance R S S R^T is never stored, its projection is built here from R and S.
// SH_DEGREE (a #define the renderer inserts: -1 plain RGB, 0..3 view-dependent colour from
// spherical harmonics in a fifth column, half floats) selects the colour source.
// Conventions follow atgs.render (OpenCV camera, pixel centers at +0.5, EWA with 0.3 px^2
// dilation, gsplat's Jacobian clamp, near plane, 3-sigma support).

in vec3 a_mean;
in vec4 a_quat;                 // w, x, y, z as int16 (any common scale: normalized here)
in vec3 a_scale;                // standard deviations
in vec4 a_opacity_rgb;          // uint16, 65535 = 1
#if SH_DEGREE >= 0
#define SH_COEFFS ((SH_DEGREE + 1) * (SH_DEGREE + 1))
#define SH_ATTRIBS ((3 * SH_COEFFS + 3) / 4)
in vec4 a_sh[SH_ATTRIBS];       // coefficient k, channel c at half number 3 k + c
uniform vec3 u_campos;          // camera centre in world space (view direction = mean - centre)
#endif

uniform mat4 u_w2c;             // OpenCV world-to-camera
uniform vec4 u_intr;            // fx, fy, cx, cy
uniform vec4 u_lim;             // Jacobian clamp: x/z in [-lim.x, lim.y], y/z in [-lim.z, lim.w]
uniform float u_near;
uniform float u_dilation;
uniform float u_scale_mod;      // scale modifier (multiplies every standard deviation)
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

#if SH_DEGREE >= 0
float sh_half(int i) { return a_sh[i / 4][i % 4]; }
vec3 sh_coeff(int k) { return vec3(sh_half(3 * k), sh_half(3 * k + 1), sh_half(3 * k + 2)); }

// 0.5 + sum_k c_k Y_k(d), clamped at 0: the real SH basis of atgs/sh.py (3DGS's signs).
vec3 sh_color(vec3 d) {
    vec3 c = 0.28209479177387814 * sh_coeff(0);
#if SH_DEGREE >= 1
    float x = d.x, y = d.y, z = d.z;
    c += 0.4886025119029199 * (-y * sh_coeff(1) + z * sh_coeff(2) - x * sh_coeff(3));
#endif
#if SH_DEGREE >= 2
    float xx = x * x, yy = y * y, zz = z * z;
    c += 1.0925484305920792 * (x * y) * sh_coeff(4)
       - 1.0925484305920792 * (y * z) * sh_coeff(5)
       + 0.31539156525252005 * (2.0 * zz - xx - yy) * sh_coeff(6)
       - 1.0925484305920792 * (x * z) * sh_coeff(7)
       + 0.5462742152960396 * (xx - yy) * sh_coeff(8);
#endif
#if SH_DEGREE >= 3
    c += -0.5900435899266435 * y * (3.0 * xx - yy) * sh_coeff(9)
       + 2.890611442640554 * (x * y * z) * sh_coeff(10)
       - 0.4570457994644658 * y * (4.0 * zz - xx - yy) * sh_coeff(11)
       + 0.3731763325901154 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh_coeff(12)
       - 0.4570457994644658 * x * (4.0 * zz - xx - yy) * sh_coeff(13)
       + 1.445305721320277 * z * (xx - yy) * sh_coeff(14)
       - 0.5900435899266435 * x * (xx - 3.0 * yy) * sh_coeff(15);
#endif
    return max(c + 0.5, vec3(0.0));
}
#endif

void main() {
    g_keep = 1;
    float opacity = a_opacity_rgb.x / 65535.0;
    vec4 pc = u_w2c * vec4(a_mean, 1.0);
    if (pc.z <= u_near || opacity < u_alpha_min) { cull(); return; }

    // Rotation of the normalized quaternion (w, x, y, z); columns of R.
    vec4 q = a_quat * inversesqrt(max(dot(a_quat, a_quat), 1e-30));
    float w = q.x, x = q.y, y = q.z, z = q.w;
    mat3 R = mat3(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y),
                  2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x),
                  2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y));
    vec3 s = a_scale * u_scale_mod;

    float fx = u_intr.x, fy = u_intr.y;
    float iz = 1.0 / pc.z;
    float tx = pc.z * clamp(pc.x * iz, -u_lim.x, u_lim.y);
    float ty = pc.z * clamp(pc.y * iz, -u_lim.z, u_lim.w);
    // Rows of J (2x3) times the rotation of the view matrix, in world space ...
    mat3 Rv = mat3(u_w2c);
    vec3 j0 = vec3(fx * iz, 0.0, -fx * tx * iz * iz);
    vec3 j1 = vec3(0.0, fy * iz, -fy * ty * iz * iz);
    // ... then in the Gaussian's frame, scaled: Sigma2d = (J W R S)(J W R S)^T + dilation I.
    vec3 u0 = ((j0 * Rv) * R) * s;   // row vector times matrix = (M^T v)^T
    vec3 u1 = ((j1 * Rv) * R) * s;
    float a = dot(u0, u0) + u_dilation;
    float b = dot(u0, u1);
    float c = dot(u1, u1) + u_dilation;
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
#if SH_DEGREE >= 0
    vec3 rgb = sh_color(normalize(a_mean - u_campos));
#else
    vec3 rgb = a_opacity_rgb.yzw / 65535.0;
#endif
    g_color = vec4(u_mode == 1 ? vec3(pc.z) : rgb, opacity);
}
