#version 430
// One ATGS frame decoded on the GPU, straight into the splat shader's vertex columns
// (atgs/viewer/gl_decode.py builds the buffers and the #defines; the torch decode it equals is
// ATGSModel.gaussians_at_frame: atgs/model/fast_decode.py, decoder.py, ATGSModel._drawn).
// One invocation per anchor of the keyframe window: the 4D hash grid's quadrilinear lookup at
// the frame's local time, the segment's temporal MLP, the four decoder heads on [f_a + f_s, f_t],
// their activations, the 3D smoothing filter, the temporal fade and the velocity shift, the
// opacity cut and the camera clearance; it writes the anchor's q Gaussians (slot a q + j).
// A Gaussian that the torch decode drops (faded-out anchor, opacity cut, inside a camera's
// clearance, not finite) is written with opacity 0: the sort and the splat shader cull it, so
// the image is the same.
//
// Defines (gl_decode.py): LEVELS, FEATS, TABLE_SIZE, RES_LIST, TIME_RES_LIST, DENSE_LIST,
// D (feature dim), TMLP_IN, TMLP_HIDDEN, Q, hidden sizes H_OPACITY, H_COV, H_COLOR, H_OFFSET,
// ANCHOR_STRIDE, weight offsets OFF_*, NUM_CENTRES, FADE (0/1).

layout(local_size_x = 64) in;

// Per anchor: ANCHOR_STRIDE floats of time-invariant values, then D floats f_a + f_s (see
// gl_decode.ANCHOR_FIELDS for the order).
layout(std430, binding = 0) readonly buffer Anchors { float anchors[]; };
layout(std430, binding = 1) readonly buffer Table { float table[]; };     // hash rows x FEATS
layout(std430, binding = 2) readonly buffer Weights { float wts[]; };     // MLPs, clearance centres
layout(std430, binding = 3) readonly buffer Active { uint window_ids[]; };  // the window's anchors
layout(std430, binding = 4) writeonly buffer OutMean { float out_mean[]; };
layout(std430, binding = 5) writeonly buffer OutQuat { uint out_quat[]; };     // int16 x4 as 2 uint
layout(std430, binding = 6) writeonly buffer OutScale { float out_scale[]; };
layout(std430, binding = 7) writeonly buffer OutOpRgb { uint out_oprgb[]; };   // uint16 x4 as 2 uint

uniform uint u_count;            // anchors in the window
uniform uint u_table_base;       // first table row of the current segment's grid in Table
uniform float u_frame;           // frame index
uniform float u_kf_factor;       // (K - 1) / (F - 1): keyframe intervals per frame (0: one keyframe)
uniform int u_grid;              // segment's temporal MLP
uniform int u_v0[LEVELS];        // lower time vertex per level
uniform float u_tw0[LEVELS];     // its weight
uniform float u_tw1[LEVELS];     // the next vertex's weight
uniform float u_fade_cut;        // anchors whose fade is below are not shown
uniform float u_opacity_cut;     // Gaussians at or below are dropped (when u_cut_on)
uniform int u_cut_on;
uniform float u_clear_r2;        // squared clearance radius (0: off)

const int RES[LEVELS] = int[LEVELS](RES_LIST);
const int TIME_RES[LEVELS] = int[LEVELS](TIME_RES_LIST);
const int DENSE[LEVELS] = int[LEVELS](DENSE_LIST);
const uint PRIME1 = 2654435761u, PRIME2 = 805459861u, PRIME3 = 3674653429u;

float sigmoid(float x) { return 1.0 / (1.0 + exp(-x)); }

float fw[2 * D];                 // decoder input [f_a + f_s, f_t]
float acc[7 * Q];                // outputs of the head being evaluated
float opac[Q];
float col[3 * Q];

// Quadrilinear lookup of one level: 8 spatial corners x the two time vertices.
void hash_level(int lv, vec3 xn, inout float h[TMLP_IN]) {
    int r = RES[lv];
    vec3 pos = clamp(xn, 0.0, 1.0) * float(r);
    vec3 base = max(min(floor(pos), vec3(float(r - 1))), vec3(0.0));
    vec3 frac = pos - base;
    ivec3 b = ivec3(base);
    float feats[FEATS];
    for (int f = 0; f < FEATS; ++f) feats[f] = 0.0;
    for (int tv = 0; tv < 2; ++tv) {
        int vertex = u_v0[lv] + tv;
        float tw = tv == 0 ? u_tw0[lv] : u_tw1[lv];
        for (int c = 0; c < 8; ++c) {
            ivec3 o = ivec3(c & 1, (c >> 1) & 1, (c >> 2) & 1);
            ivec3 p = b + o;
            float w = (o.x == 1 ? frac.x : 1.0 - frac.x) * (o.y == 1 ? frac.y : 1.0 - frac.y)
                    * (o.z == 1 ? frac.z : 1.0 - frac.z);
            uint slot;
            if (DENSE[lv] == 1) {
                uint r1 = uint(r + 1);
                slot = uint(p.x) + r1 * (uint(p.y) + r1 * uint(p.z)) + r1 * r1 * r1 * uint(vertex);
            } else {
                uint partial = (uint(p.x) ^ (uint(p.y) * PRIME1) ^ (uint(p.z) * PRIME2)) & uint(TABLE_SIZE - 1);
                slot = partial ^ ((uint(vertex) * PRIME3) & uint(TABLE_SIZE - 1));
            }
            uint row = u_table_base + uint(lv) * uint(TABLE_SIZE) + slot;
            for (int f = 0; f < FEATS; ++f) feats[f] += tw * w * table[row * uint(FEATS) + uint(f)];
        }
    }
    for (int f = 0; f < FEATS; ++f) h[lv * FEATS + f] = feats[f];
}

// One decoder head: acc[0..n_out) = W2 relu(W1 fw + b1) + b2, hidden unit by hidden unit (the
// hidden layer is never held whole).
void head(int hidden, int n_out, int off_w1, int off_b1, int off_w2t, int off_b2) {
    for (int j = 0; j < n_out; ++j) acc[j] = wts[off_b2 + j];
    for (int u = 0; u < hidden; ++u) {
        float s = wts[off_b1 + u];
        int row = off_w1 + u * 2 * D;
        for (int i = 0; i < 2 * D; ++i) s += fw[i] * wts[row + i];
        if (s <= 0.0) continue;
        int o = off_w2t + u * n_out;
        for (int j = 0; j < n_out; ++j) acc[j] += s * wts[o + j];
    }
}

void main() {
    uint k = gl_GlobalInvocationID.x;
    if (k >= u_count) return;
    uint a = window_ids[k];
    uint ab = a * uint(ANCHOR_STRIDE + D);
    vec3 mu = vec3(anchors[ab + 0u], anchors[ab + 1u], anchors[ab + 2u]);
    vec3 xn = vec3(anchors[ab + 3u], anchors[ab + 4u], anchors[ab + 5u]);
    vec3 scale_off = vec3(anchors[ab + 6u], anchors[ab + 7u], anchors[ab + 8u]);
    vec3 scale_base = vec3(anchors[ab + 9u], anchors[ab + 10u], anchors[ab + 11u]);
    vec3 velocity = vec3(anchors[ab + 12u], anchors[ab + 13u], anchors[ab + 14u]);
    float kf_frame = anchors[ab + 15u];
    float fade_width = anchors[ab + 16u];
    float smooth_var = anchors[ab + 17u];
    float inside = anchors[ab + 18u];
    bool is_static = anchors[ab + 19u] != 0.0;

    // keyframe distance and fade (atgs.model.anchor_motion)
    float dist = is_static ? 0.0 : (u_frame - kf_frame) * u_kf_factor;
    float fade = 1.0;
#if FADE
    fade = exp(-0.5 * (dist / fade_width) * (dist / fade_width));
    if (fade < u_fade_cut) {
        for (int j = 0; j < Q; ++j) {
            uint g = k * uint(Q) + uint(j);
            out_oprgb[2u * g] = 0u;
            out_oprgb[2u * g + 1u] = 0u;
        }
        return;
    }
#endif

    // temporal features f_t: hash grid at (xn, tau), then the segment's MLP
    float h[TMLP_IN];
    for (int lv = 0; lv < LEVELS; ++lv) hash_level(lv, xn, h);
    for (int i = 0; i < TMLP_IN; ++i) h[i] *= inside;
    int w1 = OFF_TW1 + u_grid * TMLP_IN * TMLP_HIDDEN, b1 = OFF_TB1 + u_grid * TMLP_HIDDEN;
    int w2 = OFF_TW2 + u_grid * TMLP_HIDDEN * D, b2 = OFF_TB2 + u_grid * D;
    for (int i = 0; i < D; ++i) {
        fw[i] = anchors[ab + uint(ANCHOR_STRIDE + i)];
        fw[D + i] = wts[b2 + i];
    }
    for (int u = 0; u < TMLP_HIDDEN; ++u) {
        float s = wts[b1 + u];
        for (int i = 0; i < TMLP_IN; ++i) s += h[i] * wts[w1 + i * TMLP_HIDDEN + u];
        if (s <= 0.0) continue;
        for (int i = 0; i < D; ++i) fw[D + i] += s * wts[w2 + u * D + i];
    }

    // heads, in GaussianDecoder.HEADS order
    head(H_OPACITY, Q, OFF_OPACITY_W1, OFF_OPACITY_B1, OFF_OPACITY_W2T, OFF_OPACITY_B2);
    for (int j = 0; j < Q; ++j) opac[j] = sigmoid(acc[j]);
    bool bad[Q];
    head(H_COV, 7 * Q, OFF_COV_W1, OFF_COV_B1, OFF_COV_W2T, OFF_COV_B2);
    for (int j = 0; j < Q; ++j) {
        uint g = k * uint(Q) + uint(j);
        vec3 s = scale_base * vec3(sigmoid(acc[7 * j]), sigmoid(acc[7 * j + 1]), sigmoid(acc[7 * j + 2]));
        vec4 q = vec4(acc[7 * j + 3], acc[7 * j + 4], acc[7 * j + 5], acc[7 * j + 6]);
        q /= max(length(q), 1e-12);
        if (smooth_var > 0.0) {  // 3D smoothing filter (atgs.model.smoothing)
            vec3 width = sqrt(s * s + smooth_var);
            vec3 ratio = s / width;
            opac[j] *= ratio.x * ratio.y * ratio.z;
            s = width;
        }
        bad[j] = any(isnan(s)) || any(isinf(s)) || any(isnan(q)) || any(isinf(q));
        out_scale[3u * g] = s.x;
        out_scale[3u * g + 1u] = s.y;
        out_scale[3u * g + 2u] = s.z;
        q /= max(length(q), 1e-8);  // packing.quat_column's normalization
        out_quat[2u * g] = packSnorm2x16(q.xy);
        out_quat[2u * g + 1u] = packSnorm2x16(q.zw);
    }
    head(H_COLOR, 3 * Q, OFF_COLOR_W1, OFF_COLOR_B1, OFF_COLOR_W2T, OFF_COLOR_B2);
    for (int j = 0; j < 3 * Q; ++j) col[j] = sigmoid(acc[j]);
    head(H_OFFSET, 3 * Q, OFF_OFFSET_W1, OFF_OFFSET_B1, OFF_OFFSET_W2T, OFF_OFFSET_B2);
    for (int j = 0; j < Q; ++j) {
        uint g = k * uint(Q) + uint(j);
        vec3 m = mu + vec3(acc[3 * j], acc[3 * j + 1], acc[3 * j + 2]) * scale_off;
        m += velocity * dist;
        float o = opac[j] * fade;
        bool keep = !bad[j] && !any(isnan(m)) && !any(isinf(m)) && !isnan(o);
        if (u_cut_on == 1) keep = keep && o > u_opacity_cut;
        for (int c = 0; c < NUM_CENTRES; ++c) {
            vec3 d = m - vec3(wts[OFF_CENTRES + 3 * c], wts[OFF_CENTRES + 3 * c + 1], wts[OFF_CENTRES + 3 * c + 2]);
            if (dot(d, d) < u_clear_r2) keep = false;
        }
        out_mean[3u * g] = m.x;
        out_mean[3u * g + 1u] = m.y;
        out_mean[3u * g + 2u] = m.z;
        vec3 rgb = vec3(col[3 * j], col[3 * j + 1], col[3 * j + 2]);
        out_oprgb[2u * g] = keep ? packUnorm2x16(vec2(o, rgb.r)) : 0u;
        out_oprgb[2u * g + 1u] = packUnorm2x16(rgb.gb);
    }
}
