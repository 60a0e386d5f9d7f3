#version 330 core
// Per-pixel Gaussian weight as atgs.render: sigma = 0.5 d^T Sigma2d^-1 d (= 0.5 |v_white|^2),
// cut beyond 3 sigma, alpha = min(0.99, o exp(-sigma)), discard below the cutoff (1/255).
// Output is premultiplied for back-to-front blending (ONE, ONE_MINUS_SRC_ALPHA); in depth mode
// the color is the view depth z (set by splat.vert), so the target accumulates sum z alpha T.

uniform float u_sigma_cut;      // 4.5 = 3 sigma
uniform float u_alpha_max;
uniform float u_alpha_min;

noperspective in vec2 v_white;
flat in vec4 v_color;

out vec4 frag;

void main() {
    float sigma = 0.5 * dot(v_white, v_white);
    if (sigma > u_sigma_cut) discard;
    float alpha = min(u_alpha_max, v_color.a * exp(-sigma));
    if (alpha < u_alpha_min) discard;
    frag = vec4(v_color.rgb * alpha, alpha);
}
