// WebGL2 splatting of one frame (of a chunk, or a decoded model frame), the same projection and
// blending as the desktop player (atgs/shaders/splat.vert, splat.geom, splat.frag,
// environment.frag): EWA with the dilation, gsplat's Jacobian clamp, the near plane, a k-sigma
// extent, alpha = min(alpha_max, o exp(-sigma)), premultiplied back-to-front blending over the
// background. A frame source (a chunk, a decoded model frame) names its layout
// (frame_layouts.js): a chunk's quantized fields stay quantized on the GPU (integer textures) and
// are dequantized in the vertex shader with the chunk's ranges; a decoded model frame's floats
// are drawn as decoded (float textures).
//
// One quad per Gaussian, drawn as one indexed draw of four vertices per quad: vertex 4 s + c is
// corner c of the s-th Gaussian back to front, whose index the shader reads from the order
// texture. Not instancing: software WebGL (SwiftShader) pays per instance, 700 against 50 ms
// a frame for 38k Gaussians at 96x72 (and llvmpipe, the desktop player found, twice the time).

import { CLAMP_MARGIN, clampLimits } from './camera.js';
import { FRAME_LAYOUTS, layoutOf } from './frame_layouts.js';
import { DepthSorter } from './sort.js';

// Texels per row of the Gaussian and order textures (entry i at (i % width, i / width)).
const TEXTURE_WIDTH = 2048;

// The splat vertex shader of a frame layout (its textures and gaussian* readers).
const splatVert = (layout) => `#version 300 es
// Vertex 4 s + c is corner c of the s-th quad back to front (u_order: the Gaussian it draws).
// The projection is splat.vert's; the quad is the rectangle of the +-k sigma ellipse in its
// eigen-frame, the shape splat.geom's triangle stands in for (WebGL2 has no geometry shader).
precision highp float;
precision highp int;
precision highp usampler2D;

uniform usampler2D u_order;                 // R32UI: Gaussian index of each quad, back to front
// the ${layout.name} layout (frame_layouts.js)
${layout.glsl}

uniform mat4 u_w2c;                         // OpenCV world-to-camera
uniform vec4 u_intr;                        // fx, fy, cx, cy
uniform vec4 u_lim;                         // Jacobian clamp: x/z in [-lim.x, lim.y], y/z in [-lim.z, lim.w]
uniform vec2 u_size;                        // target width, height in pixels
uniform float u_near;
uniform float u_dilation;
uniform float u_extent;                     // splat half-extent in standard deviations (3)
uniform float u_alpha_min;

// Position in the Gaussian's whitened frame (standard deviations along the eigen-axes): affine
// over the quad, and every vertex has w = 1, so interpolation is screen-linear and each pixel
// centre gets its exact Mahalanobis coordinates: sigma = 0.5 |v_white|^2.
out vec2 v_white;
flat out vec4 v_color;

void cull() {
    gl_Position = vec4(0.0, 0.0, 2.0, 1.0);  // outside the clip volume: nothing drawn
    v_white = vec2(0.0);
    v_color = vec4(0.0);
}

void main() {
    int slot = gl_VertexID >> 2;
    vec2 corner = vec2((gl_VertexID & 1) == 1 ? 1.0 : -1.0, (gl_VertexID & 2) == 2 ? 1.0 : -1.0);
    int i = int(texelFetch(u_order, ivec2(slot % ${TEXTURE_WIDTH}, slot / ${TEXTURE_WIDTH}), 0).x);
    ivec2 texel = ivec2(i % ${TEXTURE_WIDTH}, i / ${TEXTURE_WIDTH});
    float opacity = gaussianOpacity(texel);
    vec3 mean = gaussianMean(texel);
    vec4 pc = u_w2c * vec4(mean, 1.0);
    if (pc.z <= u_near || opacity < u_alpha_min) { cull(); return; }

    vec4 quat = gaussianRotation(texel);
    vec4 q = quat * inversesqrt(max(dot(quat, quat), 1e-30));
    float w = q.x, x = q.y, y = q.z, z = q.w;
    mat3 R = mat3(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y),
                  2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x),
                  2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y));
    vec3 s = gaussianScale(texel);

    float fx = u_intr.x, fy = u_intr.y;
    float iz = 1.0 / pc.z;
    float tx = pc.z * clamp(pc.x * iz, -u_lim.x, u_lim.y);
    float ty = pc.z * clamp(pc.y * iz, -u_lim.z, u_lim.w);
    mat3 Rv = mat3(u_w2c);
    vec3 j0 = vec3(fx * iz, 0.0, -fx * tx * iz * iz);
    vec3 j1 = vec3(0.0, fy * iz, -fy * ty * iz * iz);
    // Sigma2d = (J W R S)(J W R S)^T + dilation I, built from the rows of J W R S
    vec3 u0 = ((j0 * Rv) * R) * s;
    vec3 u1 = ((j1 * Rv) * R) * s;
    float a = dot(u0, u0) + u_dilation;
    float b = dot(u0, u1);
    float c = dot(u1, u1) + u_dilation;
    float det = a * c - b * b;
    if (!(det > 0.0)) { cull(); return; }

    vec2 center = vec2(fx * pc.x * iz + u_intr.z, fy * pc.y * iz + u_intr.w);

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
    // beyond sqrt(2 ln(o / alpha_min)) sigmas alpha < alpha_min: a faint Gaussian gets a smaller quad
    float k = min(u_extent, sqrt(max(2.0 * log(opacity / u_alpha_min), 0.0)));
    if (k <= 0.0) { cull(); return; }
    float h1 = k * sqrt(l1) * 1.0001 + 0.01, h2 = k * sqrt(l2) * 1.0001 + 0.01;

    vec2 pix = center + corner.x * h1 * e1 + corner.y * h2 * e2;
    // image row 0 is the top (OpenCV), NDC y = +1
    gl_Position = vec4(2.0 * pix.x / u_size.x - 1.0, 1.0 - 2.0 * pix.y / u_size.y, 0.0, 1.0);
    v_white = corner * vec2(h1 * inversesqrt(l1), h2 * inversesqrt(l2));
    v_color = vec4(gaussianColor(texel), opacity);
}
`;

const SPLAT_FRAG = `#version 300 es
// splat.frag: sigma = 0.5 |v_white|^2 cut beyond u_sigma_cut, alpha = min(alpha_max, o exp(-sigma)),
// discarded below alpha_min; premultiplied for ONE, ONE_MINUS_SRC_ALPHA back-to-front blending.
precision highp float;
uniform float u_sigma_cut;
uniform float u_alpha_max;
uniform float u_alpha_min;
in vec2 v_white;
flat in vec4 v_color;
out vec4 frag;

void main() {
    float sigma = 0.5 * dot(v_white, v_white);
    if (sigma > u_sigma_cut) discard;
    float alpha = min(u_alpha_max, v_color.a * exp(-sigma));
    if (alpha < u_alpha_min) discard;
    frag = vec4(v_color.rgb * alpha, alpha);
}
`;

const FULLSCREEN_VERT = `#version 300 es
// a triangle covering the viewport; no vertex buffer
void main() {
    vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
    gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}
`;

const ENVIRONMENT_FRAG = `#version 300 es
// environment.frag: each pixel starts as the map's colour along its camera ray, alpha 0, so the
// splats' blending ends at C + T env(direction).
precision highp float;
uniform sampler2D u_env;        // equirectangular: s = azimuth, t = elevation (t = 0: straight down)
uniform vec4 u_intr;            // fx, fy, cx, cy
uniform vec2 u_size;            // target width, height
uniform mat3 u_cam_to_map;      // camera axes (OpenCV) -> the map's frame (z up)
out vec4 frag;
const float PI = 3.14159265358979;

void main() {
    // GL row 0 is the image's bottom row
    vec2 px = vec2(gl_FragCoord.x, u_size.y - gl_FragCoord.y);
    vec3 d = normalize(u_cam_to_map * vec3((px - u_intr.zw) / u_intr.xy, 1.0));
    float az = atan(d.y, d.x);
    float el = asin(clamp(d.z, -1.0, 1.0));
    vec2 st = vec2((az + PI) / (2.0 * PI), (el + 0.5 * PI) / PI);
    frag = vec4(texture(u_env, st).rgb, 0.0);
}
`;

const PRESENT_FRAG = `#version 300 es
// the float target's rgb as it is (already C + T background; no sRGB conversion, as atgs-view)
precision highp float;
uniform sampler2D u_image;
out vec4 frag;
void main() {
    frag = vec4(texelFetch(u_image, ivec2(gl_FragCoord.xy), 0).rgb, 1.0);
}
`;

function compile(gl, type, source) {
  const shader = gl.createShader(type);
  gl.shaderSource(shader, source);
  gl.compileShader(shader);
  if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) {
    throw new Error(`WebGL2 shader does not compile: ${gl.getShaderInfoLog(shader)}`);
  }
  return shader;
}

function program(gl, vert, frag) {
  const p = gl.createProgram();
  gl.attachShader(p, compile(gl, gl.VERTEX_SHADER, vert));
  gl.attachShader(p, compile(gl, gl.FRAGMENT_SHADER, frag));
  gl.linkProgram(p);
  if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(`WebGL2 program does not link: ${gl.getProgramInfoLog(p)}`);
  const uniforms = {};
  const n = gl.getProgramParameter(p, gl.ACTIVE_UNIFORMS);
  for (let i = 0; i < n; i++) {
    const name = gl.getActiveUniform(p, i).name;
    uniforms[name] = gl.getUniformLocation(p, name);
  }
  return { program: p, uniforms };
}

// The draw order (sort.js), one Gaussian index a quad.
const ORDER_TEXTURE = { field: 'order', uniform: 'u_order', internal: 'R32UI', format: 'RED_INTEGER', type: 'UNSIGNED_INT' };

/** Encodes bytes as base64 (readPixels' data), in slices that String.fromCharCode accepts. */
function base64(bytes) {
  let s = '';
  for (let i = 0; i < bytes.length; i += 0x8000) s += String.fromCharCode.apply(null, bytes.subarray(i, i + 0x8000));
  return btoa(s);
}

export class Renderer {
  /**
   * Creates the WebGL2 context and programs (before the stream loads, so that a browser
   * without WebGL2 fails at once); configure() with the manifest before drawing.
   * @param {HTMLCanvasElement} canvas drawn at its width x height (the caller sizes it)
   * @throws {Error} when the browser has no WebGL2 or the shaders fail
   */
  constructor(canvas) {
    const gl = canvas.getContext('webgl2', {
      alpha: false, antialias: false, depth: false, stencil: false, premultipliedAlpha: false,
    });
    if (!gl) throw new Error('this browser has no WebGL2: the player needs it (try a current Chrome, Firefox, Safari or Edge)');
    this.canvas = canvas;
    this.gl = gl;
    this.render = null;
    this.background = [0, 0, 0];
    this.environment = null;    // {image, basis, texture}: the image is kept to upload it again after a context loss
    this.lost = false;
    this.onContextLost = () => {};
    this.onContextRestored = () => {};
    this._createResources();
    // A lost context (the GPU reset, the tab was in the background on a phone, too many
    // contexts) drops every GL object. preventDefault asks the browser to restore it; then
    // everything is built again and the caller draws the frame again.
    canvas.addEventListener('webglcontextlost', (e) => {
      e.preventDefault();
      this.lost = true;
      this.onContextLost();
    });
    canvas.addEventListener('webglcontextrestored', () => {
      this._createResources();
      if (this.environment) this._uploadEnvironment();
      this.lost = false;
      this.onContextRestored();
    });
  }

  // The programs, buffers and state of a new (or restored) context; textures come with the first draw.
  _createResources() {
    const gl = this.gl;
    // a splat program per frame layout (the one draw reads a Gaussian as its source's layout says)
    this.splats = new Map(Object.values(FRAME_LAYOUTS).map((l) => [l, program(gl, splatVert(l), SPLAT_FRAG)]));
    this.environmentProgram = program(gl, FULLSCREEN_VERT, ENVIRONMENT_FRAG);
    this.present = program(gl, FULLSCREEN_VERT, PRESENT_FRAG);
    this.sorter = new DepthSorter();
    this.textures = null;       // {layout, capacity, order, [field]: WebGLTexture}
    this.uploaded = { chunk: null, frame: -1 };
    this.target = null;         // {width, height, fbo, texture} or null: draw to the canvas
    this.floatTarget = !!(gl.getExtension('EXT_color_buffer_float') || gl.getExtension('EXT_color_buffer_half_float'));

    this.quads = gl.createVertexArray();  // no attributes: only the element buffer of the quads
    this.quadBuffer = gl.createBuffer();
    this.emptyVao = gl.createVertexArray();  // for the fullscreen triangles
  }

  /**
   * Take the stream's numerics and background.
   * @param {{render: {near: number, dilation: number, alpha_min: number, alpha_max: number, extent: number},
   *          background?: number[]}} manifest
   */
  configure(manifest) {
    this.render = manifest.render;
    this.background = manifest.background ?? [0, 0, 0];
  }

  /**
   * Use an equirectangular environment map as the background (atgs.render.environment).
   * @param {ImageBitmap|HTMLImageElement} image its top row is the map's first texel row (straight down)
   * @param {number[]} basis 9 numbers, row-major world -> map frame
   */
  setEnvironment(image, basis) {
    this.environment = { image, basis: Array.from(basis), texture: null };
    if (!this.lost) this._uploadEnvironment();
  }

  _uploadEnvironment() {
    const gl = this.gl;
    const texture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, texture);
    // the texels are linear values: no colour management, no premultiplication, no flip
    gl.pixelStorei(gl.UNPACK_COLORSPACE_CONVERSION_WEBGL, gl.NONE);
    gl.pixelStorei(gl.UNPACK_PREMULTIPLY_ALPHA_WEBGL, false);
    gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, false);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA8, gl.RGBA, gl.UNSIGNED_BYTE, this.environment.image);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.REPEAT);         // around in azimuth
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);  // clamped at the poles
    this.environment.texture = texture;
  }

  // (Re)allocates the Gaussian textures of `layout`, the order texture and the quads' element
  // buffer when a frame has more Gaussians than they hold or another layout.
  _ensureTextures(layout, count) {
    const gl = this.gl;
    if (this.textures && this.textures.layout === layout && this.textures.capacity >= count) return this.textures;
    const height = Math.max(1, Math.ceil(count / TEXTURE_WIDTH));
    if (height > gl.getParameter(gl.MAX_TEXTURE_SIZE)) {
      throw new Error(`${count} Gaussians in a chunk are more than this GPU's textures hold`);
    }
    if (this.textures) for (const t of [...this.textures.layout.textures, ORDER_TEXTURE]) gl.deleteTexture(this.textures[t.field]);
    const capacity = TEXTURE_WIDTH * height;
    const textures = { layout, capacity };
    for (const t of [...layout.textures, ORDER_TEXTURE]) {
      const tex = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D, tex);
      gl.texStorage2D(gl.TEXTURE_2D, 1, gl[t.internal], TEXTURE_WIDTH, height);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
      textures[t.field] = tex;
    }
    // quad s: two triangles over its vertices 4 s .. 4 s + 3 (corners (-1,-1), (1,-1), (-1,1), (1,1))
    const elements = new Uint32Array(6 * capacity);
    for (let q = 0, e = 0; q < capacity; q++, e += 6) {
      const v = 4 * q;
      elements[e] = v; elements[e + 1] = v + 1; elements[e + 2] = v + 2;
      elements[e + 3] = v + 2; elements[e + 4] = v + 1; elements[e + 5] = v + 3;
    }
    gl.bindVertexArray(this.quads);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.quadBuffer);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, elements, gl.STATIC_DRAW);
    gl.bindVertexArray(null);
    this.textures = textures;
    this.uploaded = { chunk: null, frame: -1 };
    this.sorter = new DepthSorter();  // the new order texture holds no order yet
    return textures;
  }

  // Uploads entries [first, first + count) of `data` (`components` per texel) into a texture of
  // the layout above: a partial first row, whole rows, a partial last row.
  _upload(texture, t, data, components, first, count) {
    const gl = this.gl;
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.bindTexture(gl.TEXTURE_2D, texture);
    const format = gl[t.format], type = gl[t.type];
    const end = first + count;
    for (let i = first; i < end;) {
      const x = i % TEXTURE_WIDTH, y = Math.floor(i / TEXTURE_WIDTH);
      const rows = x === 0 ? Math.max(1, Math.floor((end - i) / TEXTURE_WIDTH)) : 1;
      const w = rows > 1 ? TEXTURE_WIDTH : Math.min(TEXTURE_WIDTH - x, end - i);
      gl.texSubImage2D(gl.TEXTURE_2D, 0, x, y, w, rows, format, type, data, components * i);
      i += w * rows;
    }
  }

  // Uploads Gaussians [first, first + count) of every field.
  _uploadFields(fields, first, count) {
    for (const t of this.textures.layout.textures) this._upload(this.textures[t.field], t, fields[t.field], 4, first, count);
  }

  // The float target of the canvas's size, or null when the browser cannot render to one.
  _ensureTarget(width, height) {
    const gl = this.gl;
    if (!this.floatTarget) return null;
    if (this.target && this.target.width === width && this.target.height === height) return this.target;
    if (this.target) {
      gl.deleteFramebuffer(this.target.fbo);
      gl.deleteTexture(this.target.texture);
    }
    const texture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, texture);
    gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA16F, width, height);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    const fbo = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, texture, 0);
    const complete = gl.checkFramebufferStatus(gl.FRAMEBUFFER) === gl.FRAMEBUFFER_COMPLETE;
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    if (!complete) {
      gl.deleteFramebuffer(fbo);
      gl.deleteTexture(texture);
      this.floatTarget = false;
      this.target = null;
      return null;
    }
    this.target = { width, height, fbo, texture };
    return this.target;
  }

  _drawEnvironment(view) {
    const gl = this.gl;
    const { program: p, uniforms: u } = this.environmentProgram;
    const { w2c, intr } = view;
    const B = this.environment.basis;
    // cam_to_map = basis R^T (camera -> world -> map), row-major
    const M = new Float32Array(9);
    for (let r = 0; r < 3; r++) {
      for (let c = 0; c < 3; c++) {
        M[3 * r + c] = B[3 * r] * w2c[4 * c] + B[3 * r + 1] * w2c[4 * c + 1] + B[3 * r + 2] * w2c[4 * c + 2];
      }
    }
    gl.useProgram(p);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, this.environment.texture);
    gl.uniform1i(u.u_env, 0);
    gl.uniform4f(u.u_intr, intr.fx, intr.fy, intr.cx, intr.cy);
    gl.uniform2f(u.u_size, intr.width, intr.height);
    gl.uniformMatrix3fv(u.u_cam_to_map, true, M);
    gl.bindVertexArray(this.emptyVao);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
  }

  /**
   * Draw frame `local` of `chunk` as seen by `view` into the canvas.
   * @param {{layout: string, G: number, S: number, D: number, frame: (k: number) => object}} chunk a
   *   frame source: a chunk.js Chunk or a model_stream.js DecodedFrame (frame_layouts.js: its
   *   layout reads its fields and, for a chunk, its ranges)
   * @param {number} local frame index within the chunk
   * @param {{w2c: ArrayLike<number>, intr: {width: number, height: number, fx: number, fy: number, cx: number, cy: number}}} view
   *   intrinsics already fitted to the canvas size
   * @returns {{drawn: number, sorted: boolean}|null} Gaussians drawn; whether the depth order was
   *   recomputed; null while the context is lost (nothing drawn: draw again once it is restored)
   */
  draw(chunk, local, view) {
    const gl = this.gl;
    if (this.lost) return null;
    const { width, height } = this.canvas;
    const fields = chunk.frame(local);
    const layout = layoutOf(chunk);
    const textures = this._ensureTextures(layout, chunk.G);
    if (this.uploaded.chunk !== chunk) {
      this._uploadFields(fields, 0, chunk.G);
    } else if (this.uploaded.frame !== local) {
      this._uploadFields(fields, chunk.S, chunk.D);  // the static part is already there
    }
    this.uploaded = { chunk, frame: local };

    const r = this.render;
    const cull = { near: r.near, minOpacity: layout.minOpacity(r.alpha_min) };
    const { order, count } = this.sorter.sort(fields, layout.depthAffine(view.w2c, chunk), cull);
    if (this.sorter.sorted) this._upload(textures.order, ORDER_TEXTURE, order, 1, 0, count);

    const target = this._ensureTarget(width, height);
    gl.bindFramebuffer(gl.FRAMEBUFFER, target ? target.fbo : null);
    gl.viewport(0, 0, width, height);
    gl.disable(gl.BLEND);
    const [br, bg, bb] = this.background;
    gl.clearColor(br, bg, bb, 0);
    gl.clear(gl.COLOR_BUFFER_BIT);
    if (this.environment) this._drawEnvironment(view);

    const { program: p, uniforms: u } = this.splats.get(layout);
    gl.useProgram(p);
    [...layout.textures, ORDER_TEXTURE].forEach((t, unit) => {
      gl.activeTexture(gl.TEXTURE0 + unit);
      gl.bindTexture(gl.TEXTURE_2D, textures[t.field]);
      gl.uniform1i(u[t.uniform], unit);
    });
    layout.setUniforms(gl, u, chunk);
    gl.uniformMatrix4fv(u.u_w2c, true, Float32Array.from(view.w2c));
    const intr = view.intr;
    gl.uniform4f(u.u_intr, intr.fx, intr.fy, intr.cx, intr.cy);
    gl.uniform4fv(u.u_lim, clampLimits(intr, r.clamp_margin ?? CLAMP_MARGIN));  // (older exports: the constant)
    gl.uniform2f(u.u_size, width, height);
    gl.uniform1f(u.u_near, r.near);
    gl.uniform1f(u.u_dilation, r.dilation);
    gl.uniform1f(u.u_extent, r.extent);
    gl.uniform1f(u.u_alpha_min, r.alpha_min);
    gl.uniform1f(u.u_alpha_max, r.alpha_max);
    gl.uniform1f(u.u_sigma_cut, 0.5 * r.extent * r.extent);
    gl.enable(gl.BLEND);
    gl.blendEquation(gl.FUNC_ADD);
    gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
    gl.bindVertexArray(this.quads);
    gl.drawElements(gl.TRIANGLES, 6 * count, gl.UNSIGNED_INT, 0);
    gl.disable(gl.BLEND);

    if (target) {
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      gl.useProgram(this.present.program);
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, target.texture);
      gl.uniform1i(this.present.uniforms.u_image, 0);
      gl.bindVertexArray(this.emptyVao);
      gl.drawArrays(gl.TRIANGLES, 0, 3);
    }
    gl.bindVertexArray(null);
    return { drawn: count, sorted: this.sorter.sorted };
  }

  /**
   * The Gaussian textures as the last draw left them (tests: what the renderer received), read
   * back from the GPU: per field of the frame's layout (frame_layouts.js), its first 4 `count`
   * values as base64 of their float32 (a float layout), uint32 or int32 (an integer one) bytes.
   * @param {number} count Gaussians to read
   * @returns {{layout: string, fields: Object<string, string>}}
   */
  readGaussians(count) {
    const gl = this.gl;
    if (this.lost || !this.textures) throw new Error('nothing drawn: no Gaussian textures to read');
    const { layout } = this.textures;
    const rows = Math.max(1, Math.ceil(count / TEXTURE_WIDTH));
    const fbo = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    const fields = {};
    for (const t of layout.textures) {
      gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, this.textures[t.field], 0);
      const Type = { FLOAT: Float32Array, UNSIGNED_INT: Uint32Array, INT: Int32Array }[t.read];
      const px = new Type(4 * TEXTURE_WIDTH * rows);
      gl.readPixels(0, 0, TEXTURE_WIDTH, rows, gl[t.format], gl[t.read], px);
      fields[t.field] = base64(new Uint8Array(px.buffer, 0, 16 * count));
    }
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.deleteFramebuffer(fbo);
    return { layout: layout.name, fields };
  }

  /**
   * The canvas as drawn: call right after draw() (in the same task, before the browser
   * composites and clears it).
   * @returns {{width: number, height: number, encoding: 'base64', data: string}} RGBA bytes, top row first
   */
  readPixels() {
    const gl = this.gl;
    if (this.lost) throw new Error('the WebGL context is lost: nothing to read until the browser restores it');
    const { width, height } = this.canvas;
    const raw = new Uint8Array(width * height * 4);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.readPixels(0, 0, width, height, gl.RGBA, gl.UNSIGNED_BYTE, raw);
    const rows = new Uint8Array(raw.length);
    const stride = width * 4;
    for (let y = 0; y < height; y++) rows.set(raw.subarray((height - 1 - y) * stride, (height - y) * stride), y * stride);
    return { width, height, encoding: 'base64', data: base64(rows) };
  }
}
