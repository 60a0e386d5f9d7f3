// The ATGS decode of one frame on the viewer's GPU, in WebGL2 (docs/web.md, "Streaming the model").
// A port of atgs/shaders/decode.comp (the desktop player's compute shader, equal to the torch
// decode ATGSModel.gaussians_at_frame) to render-to-texture fragment passes, since WebGL2 has no
// compute shaders:
//
//   1. hash:   per anchor, the 4D hash grid's quadrilinear lookup at the frame's local time
//   2. tmlp1:  per anchor, the segment's temporal MLP, first layer (ReLU)
//   3. tmlp2:  second layer: f_t
//   4. heads1: the four decoder heads' first layers on [f_a + f_s, f_t], stacked (ReLU); their
//              f_a + f_s half is a pass of its own, run when the frame's anchors change
//   5. gauss:  per Gaussian (anchor a, slot j), the heads' second layers for that slot, their
//              activations, the 3D filter, the fade and the velocity shift, the opacity cut and
//              the camera clearance; four targets (MRT): mean + opacity, rotation, scale, colour
//
// Data lives in RGBA32F textures read with texelFetch; a "block" texture holds B texels per
// anchor (anchor a's at linear texels a B .. a B + B - 1, linear texel i at (i % W, i / W)). A
// Gaussian the torch decode drops (faded out, cut, in a camera's clearance, not finite) gets
// opacity 0, as in decode.comp. Needs EXT_color_buffer_float (float render targets).

export const TEXTURE_WIDTH = 2048;
const HEADS = ['opacity', 'cov', 'color', 'offset'];
const HEAD_WIDTH = { opacity: 1, cov: 7, color: 3, offset: 3 };  // outputs per Gaussian
const ANCHOR_HEADER = 5;  // texels of an anchor block before its features (see anchorBlocks)

const vec4s = (n) => Math.ceil(n / 4);
const rowsFor = (texels) => Math.max(1, Math.ceil(texels / TEXTURE_WIDTH));

const VERTEX = `#version 300 es
void main() {  // one triangle over the target
  vec2 p = vec2(float((gl_VertexID & 1) << 2) - 1.0, float((gl_VertexID & 2) << 1) - 1.0);
  gl_Position = vec4(p, 0.0, 1.0);
}`;

const COMMON = `#version 300 es
precision highp float;
precision highp int;
precision highp sampler2D;
#define TW ${TEXTURE_WIDTH}
ivec2 at(int i) { return ivec2(i % TW, i / TW); }
int fragmentIndex() { return int(gl_FragCoord.y) * TW + int(gl_FragCoord.x); }
`;

function hashShader(s) {
  const h = s.hash;
  return `${COMMON}
#define LEVELS ${h.levels}
#define FEATS ${h.features}
#define TABLE_SIZE ${h.table_size}
#define HB ${vec4s(h.levels * h.features)}
#define AB ${s.anchorBlock}
uniform sampler2D u_anchors;
uniform sampler2D u_hash;       // R32F: row r's feature f at linear texel r FEATS + f
uniform int u_count;
uniform int u_res[LEVELS];
uniform int u_dense[LEVELS];
uniform int u_v0[LEVELS];       // lower time vertex per level
uniform float u_tw0[LEVELS];    // its weight
uniform float u_tw1[LEVELS];    // the next vertex's weight
out vec4 o;
const uint PRIME1 = 2654435761u, PRIME2 = 805459861u, PRIME3 = 3674653429u;

float level(int lv, int f, vec3 xn) {
  int r = u_res[lv];
  vec3 pos = clamp(xn, 0.0, 1.0) * float(r);
  vec3 base = max(min(floor(pos), vec3(float(r - 1))), vec3(0.0));
  vec3 frac = pos - base;
  ivec3 b = ivec3(base);
  float sum = 0.0;
  for (int tv = 0; tv < 2; ++tv) {
    int vertex = u_v0[lv] + tv;
    float tw = tv == 0 ? u_tw0[lv] : u_tw1[lv];
    for (int c = 0; c < 8; ++c) {
      ivec3 off = ivec3(c & 1, (c >> 1) & 1, (c >> 2) & 1);
      ivec3 p = b + off;
      float w = (off.x == 1 ? frac.x : 1.0 - frac.x) * (off.y == 1 ? frac.y : 1.0 - frac.y)
              * (off.z == 1 ? frac.z : 1.0 - frac.z);
      int slot;
      if (u_dense[lv] == 1) {
        int r1 = r + 1;
        slot = p.x + r1 * (p.y + r1 * (p.z + r1 * vertex));
      } else {
        uint partial = (uint(p.x) ^ (uint(p.y) * PRIME1) ^ (uint(p.z) * PRIME2)) & uint(TABLE_SIZE - 1);
        slot = int(partial ^ ((uint(vertex) * PRIME3) & uint(TABLE_SIZE - 1)));
      }
      int row = lv * TABLE_SIZE + slot;
      sum += tw * w * texelFetch(u_hash, at(row * FEATS + f), 0).x;
    }
  }
  return sum;
}

void main() {
  int i = fragmentIndex();
  int a = i / HB, k = i - a * HB;
  if (a >= u_count) { o = vec4(0.0); return; }
  vec4 xi = texelFetch(u_anchors, at(a * AB + 1), 0);  // normalized position, inside the box
  float v[4];
  for (int c = 0; c < 4; ++c) {
    int idx = 4 * k + c;
    v[c] = idx < LEVELS * FEATS ? level(idx / FEATS, idx - (idx / FEATS) * FEATS, xi.xyz) * xi.w : 0.0;
  }
  o = vec4(v[0], v[1], v[2], v[3]);
}`;
}

// out[4 k + c] = act(init[4 k + c] + sum_i W[4 k + c][i] x[i]) for vec4 k of OUT_N per anchor:
// the input x is IN0_N vec4s of block IN0_BLOCK at IN0_OFF, then IN1_N of the second input; row u
// of W is `row` vec4s long and x meets it from vec4 `col` on; init is the bias, or a texture of
// the same layout as the output (a partial sum from an earlier pass).
function layerShader({ in0, in1, outN, relu, row = null, col = 0, init = 'bias' }) {
  const in1n = in1 ? in1.n : 0;
  return `${COMMON}
#define IN_N ${in0.n + in1n}
#define ROW ${row ?? in0.n + in1n}
uniform sampler2D u_in0;
uniform sampler2D u_in1;
uniform sampler2D u_w;
uniform sampler2D u_init;       // (init from a texture) the partial sums
uniform int u_w_off;            // row u's vec4 i at texel u_w_off + u ROW + i
uniform int u_b_off;            // the biases' vec4 k at texel u_b_off + k
uniform int u_count;
out vec4 o;

void main() {
  int i = fragmentIndex();
  int a = i / ${outN}, k = i - a * ${outN};
  if (a >= u_count) { o = vec4(0.0); return; }
  vec4 acc = ${init === 'bias' ? 'texelFetch(u_w, at(u_b_off + k), 0)' : 'texelFetch(u_init, at(i), 0)'};
  int row = u_w_off + 4 * k * ROW + ${col};
  for (int j = 0; j < IN_N; ++j) {
    vec4 x = j < ${in0.n} ? texelFetch(u_in0, at(a * ${in0.block} + ${in0.offset} + j), 0)
                          : texelFetch(u_in1, at(a * ${in1 ? in1.block : 1} + ${in1 ? in1.offset : 0} + j - ${in0.n}), 0);
    acc += vec4(dot(texelFetch(u_w, at(row + j), 0), x), dot(texelFetch(u_w, at(row + ROW + j), 0), x),
                dot(texelFetch(u_w, at(row + 2 * ROW + j), 0), x), dot(texelFetch(u_w, at(row + 3 * ROW + j), 0), x));
  }
  o = ${relu ? 'max(acc, vec4(0.0))' : 'acc'};
}`;
}

function gaussianShader(s) {
  const heads = HEADS.map((name, h) => `ivec2(${s.headOffsets[h]}, ${vec4s(s.heads[name])})`);
  return `${COMMON}
#define Q ${s.q}
#define AB ${s.anchorBlock}
#define HID ${s.hiddenBlock}
#define FADE ${s.temporal_fade ? 1 : 0}
#define MAX_HEAD ${Math.max(...HEADS.map((n) => vec4s(s.heads[n])))}
uniform sampler2D u_anchors;
uniform sampler2D u_hidden;     // the heads' hidden layers, HID vec4s per anchor
uniform sampler2D u_w;
uniform int u_count;
uniform float u_frame;
uniform float u_kf_factor;
uniform float u_fade_cut;
uniform float u_opacity_cut;
uniform int u_cut_on;
uniform float u_clear_r2;       // squared clearance radius (0: off)
uniform int u_centres;          // clearance centres (vec4s at u_centre_off)
uniform int u_centre_off;
uniform int u_w2_off[4];        // head h's output o, vec4 i at u_w2_off[h] + o n_h + i
uniform int u_b2_off[4];        // its bias at component o % 4 of texel u_b2_off[h] + o / 4
layout(location = 0) out vec4 o_mean;    // mean, opacity (0: dropped)
layout(location = 1) out vec4 o_quat;    // w, x, y, z normalized
layout(location = 2) out vec4 o_scale;   // scale, kept (1 / 0)
layout(location = 3) out vec4 o_color;   // r, g, b, 0

const ivec2 HEAD[4] = ivec2[4](${heads.join(', ')});  // each head's first hidden vec4, vec4 count

float sigmoid(float x) { return 1.0 / (1.0 + exp(-x)); }

vec4 hid[MAX_HEAD];              // the hidden layer of the head being evaluated
int head = -1;

// Output out_index of head h (its hidden layer read once for all its outputs).
float headOut(int h, int out_index, int a) {
  int n = HEAD[h].y;
  if (h != head) {
    for (int i = 0; i < n; ++i) hid[i] = texelFetch(u_hidden, at(a * HID + HEAD[h].x + i), 0);
    head = h;
  }
  float s = texelFetch(u_w, at(u_b2_off[h] + out_index / 4), 0)[out_index % 4];
  int row = u_w2_off[h] + out_index * n;
  for (int i = 0; i < n; ++i) s += dot(texelFetch(u_w, at(row + i), 0), hid[i]);
  return s;
}

bool finite3(vec3 v) { return !any(isnan(v)) && !any(isinf(v)); }

void main() {
  int g = fragmentIndex();
  int a = g / Q, j = g - a * Q;
  o_mean = vec4(0.0); o_quat = vec4(1.0, 0.0, 0.0, 0.0); o_scale = vec4(0.0); o_color = vec4(0.0);
  if (a >= u_count) return;
  int ab = a * AB;
  vec4 t0 = texelFetch(u_anchors, at(ab), 0);       // mu, keyframe frame
  vec4 t2 = texelFetch(u_anchors, at(ab + 2), 0);   // exp(v[:3]), fade width
  vec4 t3 = texelFetch(u_anchors, at(ab + 3), 0);   // exp(v[3:]), smoothing variance
  vec4 t4 = texelFetch(u_anchors, at(ab + 4), 0);   // velocity, static
  float dist = t4.w != 0.0 ? 0.0 : (u_frame - t0.w) * u_kf_factor;
  float fade = 1.0;
#if FADE
  fade = exp(-0.5 * (dist / t2.w) * (dist / t2.w));
  if (fade < u_fade_cut) return;
#endif
  float opac = sigmoid(headOut(0, j, a));
  vec3 s = t3.xyz * vec3(sigmoid(headOut(1, 7 * j, a)), sigmoid(headOut(1, 7 * j + 1, a)), sigmoid(headOut(1, 7 * j + 2, a)));
  vec4 q = vec4(headOut(1, 7 * j + 3, a), headOut(1, 7 * j + 4, a), headOut(1, 7 * j + 5, a), headOut(1, 7 * j + 6, a));
  q /= max(length(q), 1e-12);
  if (t3.w > 0.0) {  // 3D smoothing filter (atgs.model.smoothing)
    vec3 width = sqrt(s * s + t3.w);
    vec3 ratio = s / width;
    opac *= ratio.x * ratio.y * ratio.z;
    s = width;
  }
  vec3 rgb = vec3(sigmoid(headOut(2, 3 * j, a)), sigmoid(headOut(2, 3 * j + 1, a)), sigmoid(headOut(2, 3 * j + 2, a)));
  vec3 off = vec3(headOut(3, 3 * j, a), headOut(3, 3 * j + 1, a), headOut(3, 3 * j + 2, a));
  vec3 m = t0.xyz + off * t2.xyz + t4.xyz * dist;
  float op = opac * fade;
  bool keep = finite3(s) && finite3(q.xyz) && !isnan(q.w) && !isinf(q.w) && finite3(m) && !isnan(op);
  if (u_cut_on == 1) keep = keep && op > u_opacity_cut;
  for (int c = 0; c < u_centres; ++c) {
    vec3 d = m - texelFetch(u_w, at(u_centre_off + c), 0).xyz;
    if (dot(d, d) < u_clear_r2) keep = false;
  }
  o_mean = vec4(m, keep ? op : 0.0);
  o_quat = q;
  o_scale = vec4(s, keep ? 1.0 : 0.0);
  o_color = vec4(rgb, 0.0);
}`;
}

/** The WebGL2 features the decode needs, or a one-line reason it cannot run. */
export function decodeProblem(gl) {
  if (!gl.getExtension('EXT_color_buffer_float')) {
    return 'this browser cannot render to float textures (no EXT_color_buffer_float), which the model '
      + 'stream decodes into; export with --web-stream gaussians';
  }
  if (gl.getParameter(gl.MAX_DRAW_BUFFERS) < 4) return 'this browser draws to fewer than 4 targets at once; export with --web-stream gaussians';
  return null;
}

// Weights as vec4 rows: a matrix W (rows x cols) with entry (r, c) at get(r, c), its inputs in
// `segments` ([first column, count] each padded to a multiple of 4), rows padded to 4.
function packRows(out, at, rows, segments, get) {
  const n = segments.reduce((sum, [, count]) => sum + vec4s(count), 0);
  for (let r = 0; r < rows; r++) {
    let v = 0;
    for (const [first, count] of segments) {
      for (let c = 0; c < count; c++) out[4 * (at + r * n + v) + c] = get(r, first + c);
      v += vec4s(count);
    }
  }
  return vec4s(rows) * 4 * n;  // texels used
}

/**
 * Decodes frames of one model stream into float textures, on `gl` (the renderer's context).
 * @param {WebGL2RenderingContext} gl
 * @param {object} sizes the manifest's model entry
 * @param {Object<string, {shape: number[], data: Float32Array}>} weights weights.bin's tensors
 */
export class ModelDecoder {
  constructor(gl, sizes, weights) {
    const problem = decodeProblem(gl);
    if (problem) throw new Error(problem);
    this.gl = gl;
    this.sizes = sizes;
    const D = sizes.feature_dim;
    const s = {
      ...sizes, anchorBlock: ANCHOR_HEADER + vec4s(D),
      hiddenBlock: HEADS.reduce((sum, n) => sum + vec4s(sizes.heads[n]), 0),
      headOffsets: HEADS.map((n, h) => HEADS.slice(0, h).reduce((sum, m) => sum + vec4s(sizes.heads[m]), 0)),
    };
    this.s = s;
    const h = sizes.hash;
    this.hashBlock = vec4s(h.levels * h.features);
    this.tmlpBlock = vec4s(sizes.tmlp_hidden);
    this.ftBlock = vec4s(D);
    this._buildWeights(weights);
    this.programs = {
      hash: this._program(hashShader(s)),
      tmlp1: this._program(layerShader({ in0: { block: this.hashBlock, offset: 0, n: this.hashBlock }, outN: this.tmlpBlock, relu: true })),
      tmlp2: this._program(layerShader({ in0: { block: this.tmlpBlock, offset: 0, n: this.tmlpBlock }, outN: this.ftBlock, relu: false })),
      // the heads' first layers in two halves, as the torch decode (fast_decode): the f_a + f_s
      // half once per anchor set, the f_t half every frame
      pre: this._program(layerShader({
        in0: { block: s.anchorBlock, offset: ANCHOR_HEADER, n: vec4s(D) }, outN: s.hiddenBlock, relu: false,
        row: 2 * vec4s(D), col: 0,
      })),
      heads1: this._program(layerShader({
        in0: { block: this.ftBlock, offset: 0, n: this.ftBlock }, outN: s.hiddenBlock, relu: true,
        row: 2 * vec4s(D), col: vec4s(D), init: 'texture',
      })),
      gauss: this._program(gaussianShader(s)),
    };
    this.vao = gl.createVertexArray();
    this.targets = {};
    this.anchors = null;  // {key, count, texture}
    this.hash = null;     // {key, texture}
  }

  _program(fragment) {
    const gl = this.gl;
    const compile = (type, src) => {
      const sh = gl.createShader(type);
      gl.shaderSource(sh, src);
      gl.compileShader(sh);
      if (!gl.getShaderParameter(sh, gl.COMPILE_STATUS)) throw new Error(`decode shader: ${gl.getShaderInfoLog(sh)}`);
      return sh;
    };
    const p = gl.createProgram();
    gl.attachShader(p, compile(gl.VERTEX_SHADER, VERTEX));
    gl.attachShader(p, compile(gl.FRAGMENT_SHADER, fragment));
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(`decode program: ${gl.getProgramInfoLog(p)}`);
    const uniforms = {};
    const n = gl.getProgramParameter(p, gl.ACTIVE_UNIFORMS);
    for (let i = 0; i < n; i++) {
      const name = gl.getActiveUniform(p, i).name.replace(/\[0\]$/, '');
      uniforms[name] = gl.getUniformLocation(p, name);
    }
    return { program: p, uniforms };
  }

  // A float texture of `texels` RGBA (or R) texels, filled from `data` if given.
  _texture(texels, data = null, single = false) {
    const gl = this.gl;
    const rows = rowsFor(texels);
    if (rows > gl.getParameter(gl.MAX_TEXTURE_SIZE)) {
      throw new Error(`the model's frames need ${texels} texels in a texture, more than this GPU's textures hold; `
        + 'export with --web-stream gaussians');
    }
    const tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.texStorage2D(gl.TEXTURE_2D, 1, single ? gl.R32F : gl.RGBA32F, TEXTURE_WIDTH, rows);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    if (data) {
      const full = new Float32Array(TEXTURE_WIDTH * rows * (single ? 1 : 4));
      full.set(data.subarray(0, Math.min(data.length, full.length)));
      gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
      gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, TEXTURE_WIDTH, rows, single ? gl.RED : gl.RGBA, gl.FLOAT, full);
    }
    return { texture: tex, rows };
  }

  // Every MLP in one RGBA32F texture, as vec4 rows (the layer shader's layout).
  _buildWeights(w) {
    const s = this.s, D = s.feature_dim, h = s.hash;
    const inHash = h.levels * h.features, hidden = s.tmlp_hidden;
    const M = w.tmlp_w1.shape[0];
    const data = [];  // grows as it is filled; holes are zeros (padding)
    let at = 0;
    const bias = (b, n, offset = 0) => {  // n values of b from offset, as vec4s
      const start = at;
      for (let i = 0; i < n; i++) data[4 * at + i] = b.data[offset + i];
      at += vec4s(n);
      return start;
    };
    this.offsets = { tmlp: [] };
    for (let m = 0; m < M; m++) {
      const w1 = w.tmlp_w1.data, w2 = w.tmlp_w2.data;
      const o = {};
      o.w1 = at;  // row u: w1[m][i][u] over i
      at += packRows(data, at, hidden, [[0, inHash]], (u, i) => w1[(m * inHash + i) * hidden + u]);
      o.b1 = bias(w.tmlp_b1, hidden, m * hidden);
      o.w2 = at;  // row d: w2[m][u][d] over u
      at += packRows(data, at, D, [[0, hidden]], (d, u) => w2[(m * hidden + u) * D + d]);
      o.b2 = bias(w.tmlp_b2, D, m * D);
      this.offsets.tmlp.push(o);
    }
    // the heads' first layers stacked (each head's rows padded to 4), inputs [f_a + f_s, f_t]
    this.offsets.heads1 = at;
    for (const n of HEADS) {
      const W = w[`${n}.w1`].data, H = s.heads[n];
      at += packRows(data, at, H, [[0, D], [D, D]], (r, c) => W[r * 2 * D + c]);
    }
    this.offsets.headsB1 = at;
    for (const n of HEADS) bias(w[`${n}.b1`], s.heads[n]);
    this.offsets.w2 = [];
    this.offsets.b2 = [];
    for (const n of HEADS) {
      const W = w[`${n}.w2`].data, H = s.heads[n], outs = HEAD_WIDTH[n] * s.q;
      this.offsets.w2.push(at);
      at += packRows(data, at, outs, [[0, H]], (r, c) => W[r * H + c]);
      this.offsets.b2.push(bias(w[`${n}.b2`], outs));
    }
    this.offsets.centres = at;
    this.centres = w.centres ? w.centres.shape[0] : 0;
    for (let c = 0; c < this.centres; c++, at++) for (let k = 0; k < 3; k++) data[4 * at + k] = w.centres.data[3 * c + k];
    this.weights = this._texture(at, Float32Array.from({ length: 4 * at }, (_, i) => data[i] ?? 0)).texture;
  }

  /**
   * Lay out a frame's anchors (the anchor parts it needs, in order) in the anchor block texture.
   * @param {string} key what identifies this set (the same key: nothing is uploaded)
   * @param {{keyframe: number, tensors: object}[]} parts
   */
  setAnchors(key, parts) {
    if (this.anchors && this.anchors.key === key) return;
    const s = this.s, D = s.feature_dim, AB = s.anchorBlock;
    const count = parts.reduce((sum, p) => sum + p.tensors.mu.shape[0], 0);
    const data = new Float32Array(4 * AB * Math.max(1, count));
    const f = Math.fround;
    const lo = s.bbox_min.map(f), hi = s.bbox_max.map(f);
    const span = [0, 1, 2].map((c) => f(hi[c] - lo[c]));
    const [wMin, wMax] = s.fade_width;
    let a = 0;
    for (const { keyframe, tensors: t } of parts) {
      const n = t.mu.shape[0];
      const kfFrame = keyframe < 0 ? 0 : s.keyframe_frames[keyframe];
      for (let i = 0; i < n; i++, a++) {
        const b = 4 * AB * a;
        let inside = 1;
        for (let c = 0; c < 3; c++) {
          const mu = t.mu.data[3 * i + c];
          const xn = f(f(mu - lo[c]) / span[c]);  // as torch: (mu - bbox_min) / (bbox_max - bbox_min) in float32
          if (!(xn >= 0 && xn <= 1)) inside = 0;
          data[b + c] = mu;
          data[b + 4 + c] = xn;
          data[b + 8 + c] = Math.exp(t.log_scale.data[6 * i + c]);
          data[b + 12 + c] = Math.exp(t.log_scale.data[6 * i + 3 + c]);
          data[b + 16 + c] = t.velocity ? t.velocity.data[3 * i + c] : 0;
        }
        data[b + 3] = kfFrame;
        data[b + 7] = inside;
        data[b + 11] = t.fade ? Math.min(Math.max(f(Math.exp(t.fade.data[i])), wMin), wMax ?? Infinity) : 1;
        data[b + 15] = t.smoothing ? t.smoothing.data[i] : 0;
        data[b + 19] = keyframe < 0 ? 1 : 0;
        for (let c = 0; c < D; c++) data[b + 4 * ANCHOR_HEADER + c] = t.feature.data[D * i + c];
      }
    }
    if (this.anchors) this.gl.deleteTexture(this.anchors.texture);
    this.anchors = { key, count, texture: this._texture(count * AB, data).texture };
  }

  /** Upload a segment's hash grid (the same key: nothing is uploaded). */
  setHash(key, tensors) {
    if (this.hash && this.hash.key === key) return;
    if (this.hash) this.gl.deleteTexture(this.hash.texture);
    this.hash = { key, texture: this._texture(tensors.hash.data.length, tensors.hash.data, true).texture };
  }

  // The render target `name` of `texels` texels per attachment (reallocated when too small).
  _target(name, texels, attachments = 1) {
    const gl = this.gl;
    const rows = rowsFor(texels);
    const t = this.targets[name];
    if (t && t.rows >= rows) return t;
    if (t) {
      gl.deleteFramebuffer(t.fbo);
      for (const tex of t.textures) gl.deleteTexture(tex);
    }
    const fbo = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    const textures = [];
    for (let i = 0; i < attachments; i++) {
      const tex = this._texture(rows * TEXTURE_WIDTH).texture;
      gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0 + i, gl.TEXTURE_2D, tex, 0);
      textures.push(tex);
    }
    gl.drawBuffers(textures.map((_, i) => gl.COLOR_ATTACHMENT0 + i));
    if (gl.checkFramebufferStatus(gl.FRAMEBUFFER) !== gl.FRAMEBUFFER_COMPLETE) {
      throw new Error('this browser cannot render to float textures; export with --web-stream gaussians');
    }
    this.targets[name] = { fbo, textures, rows };
    return this.targets[name];
  }

  // One pass: program `name` over `texels` fragments into target `target`, with textures bound.
  _pass(name, target, texels, textures, set) {
    const gl = this.gl;
    const { program, uniforms: u } = this.programs[name];
    gl.bindFramebuffer(gl.FRAMEBUFFER, target.fbo);
    gl.viewport(0, 0, TEXTURE_WIDTH, rowsFor(texels));
    gl.useProgram(program);
    Object.entries(textures).forEach(([uniform, tex], unit) => {
      gl.activeTexture(gl.TEXTURE0 + unit);
      gl.bindTexture(gl.TEXTURE_2D, tex);
      gl.uniform1i(u[uniform], unit);
    });
    gl.uniform1i(u.u_count, this.anchors.count);
    set(u);
    gl.bindVertexArray(this.vao);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
  }

  /**
   * Decode one frame (setAnchors and setHash first) and read it back.
   * @param {{frame: number, segment: number, corners: number[][]}} entry the manifest's frame entry
   * @returns {{count: number, mean: Float32Array, quat: Float32Array, scale: Float32Array, color: Float32Array}}
   *   per Gaussian slot (anchor a, slot j at a q + j) RGBA: mean + opacity, rotation, scale + kept, colour
   */
  decode(entry) {
    const gl = this.gl, s = this.s;
    const n = this.anchors.count;
    const blend = gl.isEnabled(gl.BLEND);
    gl.disable(gl.BLEND);
    const hash = this._target('hash', n * this.hashBlock);
    const t1 = this._target('tmlp1', n * this.tmlpBlock);
    const ft = this._target('ft', n * this.ftBlock);
    const pre = this._target('pre', n * s.hiddenBlock);
    const hidden = this._target('hidden', n * s.hiddenBlock);
    const out = this._target('gauss', n * s.q, 4);
    const h = s.hash;
    this._pass('hash', hash, n * this.hashBlock, { u_anchors: this.anchors.texture, u_hash: this.hash.texture }, (u) => {
      gl.uniform1iv(u.u_res, h.res);
      gl.uniform1iv(u.u_dense, h.dense.map(Number));
      gl.uniform1iv(u.u_v0, entry.corners.map((c) => c[0]));
      gl.uniform1fv(u.u_tw0, entry.corners.map((c) => c[1]));
      gl.uniform1fv(u.u_tw1, entry.corners.map((c) => c[2]));
    });
    const o = this.offsets.tmlp[entry.segment];
    const layer = (w, b) => (u) => { gl.uniform1i(u.u_w_off, w); gl.uniform1i(u.u_b_off, b); };
    this._pass('tmlp1', t1, n * this.tmlpBlock, { u_in0: hash.textures[0], u_in1: hash.textures[0], u_w: this.weights }, layer(o.w1, o.b1));
    this._pass('tmlp2', ft, n * this.ftBlock, { u_in0: t1.textures[0], u_in1: t1.textures[0], u_w: this.weights }, layer(o.w2, o.b2));
    if (this.preOf !== this.anchors || pre !== this.preTarget) {
      this._pass('pre', pre, n * s.hiddenBlock, { u_in0: this.anchors.texture, u_in1: this.anchors.texture, u_w: this.weights,
        u_init: this.anchors.texture }, layer(this.offsets.heads1, this.offsets.headsB1));
      this.preOf = this.anchors;
      this.preTarget = pre;
    }
    this._pass('heads1', hidden, n * s.hiddenBlock, { u_in0: ft.textures[0], u_in1: ft.textures[0], u_w: this.weights,
      u_init: pre.textures[0] }, layer(this.offsets.heads1, this.offsets.headsB1));
    this._pass('gauss', out, n * s.q, { u_anchors: this.anchors.texture, u_hidden: hidden.textures[0], u_w: this.weights }, (u) => {
      gl.uniform1f(u.u_frame, entry.frame);
      gl.uniform1f(u.u_kf_factor, s.kf_factor);
      gl.uniform1f(u.u_fade_cut, s.fade_cut);
      gl.uniform1f(u.u_opacity_cut, s.opacity_threshold);
      gl.uniform1i(u.u_cut_on, s.opacity_threshold > 0 ? 1 : 0);
      gl.uniform1f(u.u_clear_r2, s.clearance_radius * s.clearance_radius);
      gl.uniform1i(u.u_centres, s.clearance_radius > 0 ? this.centres : 0);
      gl.uniform1i(u.u_centre_off, this.offsets.centres);
      gl.uniform1iv(u.u_w2_off, this.offsets.w2);
      gl.uniform1iv(u.u_b2_off, this.offsets.b2);
    });
    const count = n * s.q;
    const rows = rowsFor(count);
    const read = (i) => {
      const px = new Float32Array(4 * TEXTURE_WIDTH * rows);
      gl.readBuffer(gl.COLOR_ATTACHMENT0 + i);
      gl.readPixels(0, 0, TEXTURE_WIDTH, rows, gl.RGBA, gl.FLOAT, px);
      return px;
    };
    const result = { count, mean: read(0), quat: read(1), scale: read(2), color: read(3) };
    gl.readBuffer(gl.COLOR_ATTACHMENT0);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    if (blend) gl.enable(gl.BLEND);
    return result;
  }
}
