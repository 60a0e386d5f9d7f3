#version 330 core
// Color mode's present: the splatting target as is (its rgb already holds C + T bg). A bare
// texture fetch is llvmpipe's fast "linear" path: 2.3 against 5.0 ms for 160x120 -> 640x480.
// Alpha (1 - T) is written too (masking it loses the fast path); the window has no alpha bits.
uniform sampler2D u_image;
in vec2 v_uv;
out vec4 frag;

void main() {
    frag = texture(u_image, v_uv);
}
