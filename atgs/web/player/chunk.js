// One chunk file of the web stream (docs/web.md, "A chunk file"): gzip inflate and the planar,
// byte-plane-delta quantized layout. Pure logic (no DOM, no WebGL) so that Node tests it.

import { readAll } from './read.js';

export const MAGIC = 'ATGC';
export const VERSION = 1;
export const HEADER_BYTES = 48;
/** Bytes per Gaussian in a block: position 3 x u16, log-scale 3 x u8, rotation 4 x i8, opacity u8, colour 3 x u8. */
export const RECORD_BYTES = 17;

/**
 * Inflate gzip bytes with the platform's DecompressionStream (browsers, Node 20).
 * @param {ArrayBuffer|Uint8Array} buffer gzip (RFC 1952) bytes
 * @param {number} [expected] the inflated size if known (inflated into one buffer of that size)
 * @returns {Promise<Uint8Array>} the inflated bytes
 * @throws {Error} "not valid gzip data" when the bytes do not inflate
 */
export async function inflate(buffer, expected) {
  // a stream of the bytes themselves (a Blob would copy them first)
  const bytes = buffer instanceof Uint8Array ? buffer : new Uint8Array(buffer);
  const source = new ReadableStream({ start(c) { c.enqueue(bytes); c.close(); } });
  const stream = source.pipeThrough(new DecompressionStream('gzip'));
  try {
    return await readAll(stream.getReader(), { expected });
  } catch {
    // the platforms' own messages say little (Chrome's reads "Failed to fetch")
    throw new Error('not valid gzip data');
  }
}

// Byte offsets of each field's planes inside a block of n Gaussians (component-planar; a u16
// component is its n low bytes then its n high bytes).
function planeOffsets(n) {
  return { position: 0, logScale: 6 * n, rotation: 9 * n, opacity: 13 * n, color: 14 * n };
}

/**
 * Quantized fields of every Gaussian of one frame, interleaved four to a Gaussian as the
 * renderer's integer textures take them (Gaussian i at [4 i, 4 i + 4)):
 * - position   Uint16Array  x, y, z, 0        (RGBA16UI)
 * - scaleOpacity Uint8Array log-scale x, y, z, opacity (RGBA8UI)
 * - rotation   Int8Array    w, x, y, z        (RGBA8I)
 * - color      Uint8Array   r, g, b, 0        (RGBA8UI)
 * - opacity    scaleOpacity itself: the array with the opacity at 4 i + 3, as the depth sort reads it
 * @typedef {{count: number, position: Uint16Array, scaleOpacity: Uint8Array,
 *            rotation: Int8Array, color: Uint8Array, opacity: Uint8Array, geometryVersion: number}} FrameFields
 * geometryVersion changes only when a position or opacity changed from the frame returned
 * before (a depth sort of the previous frame is still valid while it stays the same).
 */

// Writes the n records of a planar block (bytes) into the interleaved fields at Gaussians [first, first + n).
function unpackBlock(bytes, n, fields, first) {
  const o = planeOffsets(n);
  const { position, scaleOpacity, rotation, color } = fields;
  for (let c = 0; c < 3; c++) {
    const lo = o.position + 2 * c * n, hi = lo + n;
    for (let i = 0, t = 4 * first + c; i < n; i++, t += 4) position[t] = bytes[lo + i] | (bytes[hi + i] << 8);
    const s = o.logScale + c * n;
    for (let i = 0, t = 4 * first + c; i < n; i++, t += 4) scaleOpacity[t] = bytes[s + i];
    const k = o.color + c * n;
    for (let i = 0, t = 4 * first + c; i < n; i++, t += 4) color[t] = bytes[k + i];
  }
  for (let i = 0, t = 4 * first + 3; i < n; i++, t += 4) scaleOpacity[t] = bytes[o.opacity + i];
  for (let c = 0; c < 4; c++) {
    const r = o.rotation + c * n;
    // Int8Array stores the byte's two's complement value: 255 -> -1
    for (let i = 0, t = 4 * first + c; i < n; i++, t += 4) rotation[t] = bytes[r + i];
  }
}

// True when a delta block changes no position or opacity byte (then the depth order holds).
function keepsGeometry(delta, n) {
  const o = planeOffsets(n);
  for (let i = o.position; i < o.logScale; i++) if (delta[i] !== 0) return false;
  for (let i = o.opacity; i < o.color; i++) if (delta[i] !== 0) return false;
  return true;
}

/** A parsed chunk: header values plus frame(k). See parseChunk. The renderer draws it as a frame
 * source of layout "quantized" (frame_layouts.js). */
export class Chunk {
  /** @param {Uint8Array} bytes inflated chunk bytes, already validated by parseChunk */
  constructor(bytes, header) {
    Object.assign(this, header);
    this.layout = 'quantized';
    this.bytes = bytes;
    this.staticBytes = RECORD_BYTES * this.S;
    this.blockBytes = RECORD_BYTES * this.D;
    const G = this.G;
    const scaleOpacity = new Uint8Array(4 * G);
    this.fields = {
      count: G,
      position: new Uint16Array(4 * G),
      scaleOpacity,
      rotation: new Int8Array(4 * G),
      color: new Uint8Array(4 * G),
      opacity: scaleOpacity,
      geometryVersion: 0,
    };
    // The static Gaussians are the same in every frame: unpacked once.
    unpackBlock(bytes.subarray(HEADER_BYTES, HEADER_BYTES + this.staticBytes), this.S, this.fields, 0);
    this.state = new Uint8Array(this.blockBytes);  // running planar bytes of the dynamic block
    this.stateFrame = -1;  // the frame whose bytes state holds (-1: none yet)
  }

  /** The planar bytes of frame block k (values for k = 0, byte-plane deltas after). */
  block(k) {
    const start = HEADER_BYTES + this.staticBytes + k * this.blockBytes;
    return this.bytes.subarray(start, start + this.blockBytes);
  }

  /**
   * The quantized fields of frame k (0 <= k < F). Playing forward costs one block per frame:
   * the running byte state is kept, so frame k after frame k - 1 adds one delta block; going
   * back restarts from frame 0. The returned arrays are the chunk's own and are overwritten by
   * the next call.
   * @param {number} k frame within the chunk
   * @returns {FrameFields}
   */
  frame(k) {
    if (!Number.isInteger(k) || k < 0 || k >= this.F) {
      throw new RangeError(`frame ${k} is outside this chunk's ${this.F} frames`);
    }
    if (k === this.stateFrame) return this.fields;
    let moved = false;
    if (k < this.stateFrame || this.stateFrame < 0) {
      this.state.set(this.block(0));
      this.stateFrame = 0;
      moved = true;
    }
    const state = this.state;
    for (let f = this.stateFrame + 1; f <= k; f++) {
      const delta = this.block(f);
      // a Uint8Array store wraps modulo 256, which is exactly the per-plane delta rule
      for (let i = 0; i < state.length; i++) state[i] += delta[i];
      if (!keepsGeometry(delta, this.D)) moved = true;
    }
    this.stateFrame = k;
    unpackBlock(state, this.D, this.fields, this.S);
    if (moved) this.fields.geometryVersion++;
    return this.fields;
  }
}

/**
 * Parse the inflated bytes of a chunk (no copy; frames are reconstructed on demand).
 * @param {Uint8Array} bytes inflated chunk
 * @returns {Chunk} with F, G, S, D (= G - S), ranges {posMin, posMax, logScaleMin, logScaleMax}
 *   and frame(k)
 * @throws {Error} bad magic, unsupported version, sizes that do not add up, truncated data
 */
export function parseChunk(bytes) {
  if (!(bytes instanceof Uint8Array)) bytes = new Uint8Array(bytes);
  if (bytes.length < HEADER_BYTES) {
    throw new Error(`truncated chunk: ${bytes.length} bytes, shorter than the ${HEADER_BYTES}-byte header`);
  }
  const magic = String.fromCharCode(bytes[0], bytes[1], bytes[2], bytes[3]);
  if (magic !== MAGIC) throw new Error(`not an ATGS chunk (magic ${JSON.stringify(magic)}, expected "${MAGIC}")`);
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const version = view.getUint16(4, true);
  if (version !== VERSION) throw new Error(`chunk version ${version} is not supported (this player reads version ${VERSION})`);
  const F = view.getUint16(6, true);
  const G = view.getUint32(8, true);
  const S = view.getUint32(12, true);
  if (F < 1) throw new Error('chunk holds no frames (F = 0)');
  if (S > G) throw new Error(`chunk sizes do not add up: ${S} static Gaussians of ${G}`);
  const f32 = (offset) => view.getFloat32(offset, true);
  const ranges = {
    posMin: [f32(16), f32(20), f32(24)],
    posMax: [f32(28), f32(32), f32(36)],
    logScaleMin: f32(40),
    logScaleMax: f32(44),
  };
  const expected = HEADER_BYTES + RECORD_BYTES * S + F * RECORD_BYTES * (G - S);
  if (bytes.length < expected) {
    throw new Error(`truncated chunk: ${bytes.length} of ${expected} bytes (F=${F}, G=${G}, S=${S})`);
  }
  if (bytes.length > expected) {
    throw new Error(`chunk sizes do not add up: ${bytes.length} bytes, ${expected} expected for F=${F}, G=${G}, S=${S}`);
  }
  return new Chunk(bytes, { version, F, G, S, D: G - S, ranges });
}
