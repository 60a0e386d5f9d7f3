#version 330 core
// Shows the splatting target on screen: color as is, depth (sum z alpha / alpha) through a
// colormap between u_range.x and u_range.y, or alpha as gray.
uniform sampler2D u_image;
uniform int u_mode;             // 0 color, 1 depth, 2 alpha
uniform vec2 u_range;           // depth range for the colormap
uniform vec3 u_background;
in vec2 v_uv;
out vec4 frag;

vec3 colormap(float x) {
    // Smooth blue -> cyan -> yellow -> red ramp (cheap polynomial, not a licensed LUT).
    x = clamp(x, 0.0, 1.0);
    vec3 c = vec3(clamp(1.5 - abs(4.0 * x - 3.0), 0.0, 1.0),
                  clamp(1.5 - abs(4.0 * x - 2.0), 0.0, 1.0),
                  clamp(1.5 - abs(4.0 * x - 1.0), 0.0, 1.0));
    return c;
}

void main() {
    vec4 s = texture(u_image, v_uv);
    vec3 rgb;
    if (u_mode == 0) {
        rgb = s.rgb;
    } else if (u_mode == 1) {
        float z = s.a > 1e-4 ? s.r / s.a : u_range.y;
        float x = (z - u_range.x) / max(u_range.y - u_range.x, 1e-6);
        rgb = mix(u_background, colormap(1.0 - x), s.a);
    } else {
        rgb = vec3(s.a);
    }
    frag = vec4(rgb, 1.0);
}
