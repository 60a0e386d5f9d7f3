// How a frame's Gaussians sit in the renderer's textures: the strategies behind renderer.js's one
// draw. A frame source (a chunk.js Chunk, a model_stream.js DecodedFrame) names its layout; the
// layout says which textures hold the fields, how the splat shader reads a Gaussian from them,
// and what the depth sort (sort.js) reads from the fields:
// - "quantized": a chunk file's integer fields, de-quantized in the shader over the chunk's ranges
// - "float": a decoded model frame's float32 read-backs as they are (no quantization on the way)
// Each layout's GLSL defines gaussianOpacity, gaussianMean, gaussianRotation (w, x, y, z, any
// norm), gaussianScale (linear) and gaussianColor of a texel.

import { depthAffine, depthAffineOfFloats } from './sort.js';

/** The texture of each field: `read` is what readPixels takes to read it back (tests). */
const QUANTIZED_TEXTURES = [
  { field: 'position', uniform: 'u_position', internal: 'RGBA16UI', format: 'RGBA_INTEGER', type: 'UNSIGNED_SHORT', read: 'UNSIGNED_INT' },
  { field: 'scaleOpacity', uniform: 'u_scale_opacity', internal: 'RGBA8UI', format: 'RGBA_INTEGER', type: 'UNSIGNED_BYTE', read: 'UNSIGNED_INT' },
  { field: 'rotation', uniform: 'u_rotation', internal: 'RGBA8I', format: 'RGBA_INTEGER', type: 'BYTE', read: 'INT' },
  { field: 'color', uniform: 'u_color', internal: 'RGBA8UI', format: 'RGBA_INTEGER', type: 'UNSIGNED_BYTE', read: 'UNSIGNED_INT' },
];

const QUANTIZED_GLSL = `
precision highp usampler2D;
precision highp isampler2D;
uniform usampler2D u_position;              // RGBA16UI: x, y, z, _
uniform usampler2D u_scale_opacity;         // RGBA8UI: log-scale x, y, z, opacity
uniform isampler2D u_rotation;              // RGBA8I: w, x, y, z (any common scale)
uniform usampler2D u_color;                 // RGBA8UI: r, g, b, _
uniform vec3 u_pos_min;
uniform vec3 u_pos_max;
uniform vec2 u_log_scale;                   // lo, hi

float gaussianOpacity(ivec2 texel) { return float(texelFetch(u_scale_opacity, texel, 0).w) / 255.0; }
vec3 gaussianMean(ivec2 texel) {
    return u_pos_min + vec3(texelFetch(u_position, texel, 0).xyz) / 65535.0 * (u_pos_max - u_pos_min);
}
vec4 gaussianRotation(ivec2 texel) { return vec4(texelFetch(u_rotation, texel, 0)); }
vec3 gaussianScale(ivec2 texel) {
    return exp(u_log_scale.x + vec3(texelFetch(u_scale_opacity, texel, 0).xyz) / 255.0 * (u_log_scale.y - u_log_scale.x));
}
vec3 gaussianColor(ivec2 texel) { return vec3(texelFetch(u_color, texel, 0).xyz) / 255.0; }
`;

// the four RGBA32F read-backs of model_decode.js, each in a texture of its own
const FLOAT_TEXTURES = ['mean', 'quat', 'scale', 'color'].map((field) => (
  { field, uniform: `u_${field}`, internal: 'RGBA32F', format: 'RGBA', type: 'FLOAT', read: 'FLOAT' }));

const FLOAT_GLSL = `
uniform highp sampler2D u_mean;             // RGBA32F: x, y, z, opacity (0: dropped)
uniform highp sampler2D u_quat;             // RGBA32F: w, x, y, z
uniform highp sampler2D u_scale;            // RGBA32F: linear scale x, y, z, _
uniform highp sampler2D u_color;            // RGBA32F: r, g, b, _

float gaussianOpacity(ivec2 texel) { return texelFetch(u_mean, texel, 0).w; }
vec3 gaussianMean(ivec2 texel) { return texelFetch(u_mean, texel, 0).xyz; }
vec4 gaussianRotation(ivec2 texel) { return texelFetch(u_quat, texel, 0); }
vec3 gaussianScale(ivec2 texel) { return texelFetch(u_scale, texel, 0).xyz; }
vec3 gaussianColor(ivec2 texel) { return texelFetch(u_color, texel, 0).xyz; }
`;

/**
 * @typedef {object} FrameLayout
 * @property {string} name
 * @property {object[]} textures the field textures, in texture-unit order
 * @property {string} glsl the splat shader's declarations and gaussian* readers
 * @property {(gl: WebGL2RenderingContext, uniforms: object, source: object) => void} setUniforms
 * @property {(w2c: ArrayLike<number>, source: object) => Float64Array} depthAffine view depth of the
 *   sort's stored position: z = a[0] x + a[1] y + a[2] z + a[3]
 * @property {(alphaMin: number) => number} minOpacity the stored opacity below which the shader
 *   culls anyway (the sort leaves those out)
 */

/** @type {Object<string, FrameLayout>} */
export const FRAME_LAYOUTS = {
  quantized: {
    name: 'quantized',
    textures: QUANTIZED_TEXTURES,
    glsl: QUANTIZED_GLSL,
    setUniforms(gl, u, chunk) {
      const { posMin, posMax, logScaleMin, logScaleMax } = chunk.ranges;
      gl.uniform3fv(u.u_pos_min, posMin);
      gl.uniform3fv(u.u_pos_max, posMax);
      gl.uniform2f(u.u_log_scale, logScaleMin, logScaleMax);
    },
    depthAffine: (w2c, chunk) => depthAffine(w2c, chunk.ranges.posMin, chunk.ranges.posMax),
    // the opacity byte: opacity / 255 < alpha_min
    minOpacity: (alphaMin) => Math.max(0, Math.ceil(alphaMin * 255 - 1e-9)),
  },
  float: {
    name: 'float',
    textures: FLOAT_TEXTURES,
    glsl: FLOAT_GLSL,
    setUniforms() {},
    depthAffine: (w2c) => depthAffineOfFloats(w2c),
    // the shader compares the float32 opacity with the float32 uniform
    minOpacity: (alphaMin) => Math.fround(alphaMin),
  },
};

/** The layout a frame source names; one clear line for an unknown one. */
export function layoutOf(source) {
  const layout = FRAME_LAYOUTS[source.layout];
  if (!layout) throw new Error(`a frame source of layout ${JSON.stringify(source.layout)}: the renderer draws ${Object.keys(FRAME_LAYOUTS).join(' or ')}`);
  return layout;
}
