#version 330 core
// Background by direction (atgs.render.environment.EnvironmentMap): each pixel of the splatting
// target starts as the map's colour along its camera ray, with alpha 0, so that the splats'
// back-to-front blending ends at C + T env(direction), as atgs.render.rasterize composites it.
uniform sampler2D u_env;        // equirectangular: s = azimuth, t = elevation (t = 0: straight down)
uniform vec4 u_intr;            // fx, fy, cx, cy of the target
uniform vec2 u_size;            // target width, height
uniform mat3 u_cam_to_map;      // camera axes (OpenCV) -> the map's frame (z up)
out vec4 frag;

const float PI = 3.14159265358979;

void main() {
    // the target's GL row 0 is the image's bottom row (read() flips it)
    vec2 px = vec2(gl_FragCoord.x, u_size.y - gl_FragCoord.y);
    vec3 d = normalize(u_cam_to_map * vec3((px - u_intr.zw) / u_intr.xy, 1.0));
    float az = atan(d.y, d.x);
    float el = asin(clamp(d.z, -1.0, 1.0));
    vec2 st = vec2((az + PI) / (2.0 * PI), (el + 0.5 * PI) / PI);
    frag = vec4(texture(u_env, st).rgb, 0.0);
}
