// A model stream (manifest kind "model", docs/web.md "Streaming the model"): the part files the
// frames near the playhead need, fetched in playing order, and each frame decoded on the GPU
// (model_decode.js) when the player asks for it. Offers the player the Stream interface of
// stream.js with one frame a unit: locate, setPlayhead, decodedNow, chunk, failed, url, units.
// What it hands the renderer is a one-frame stand-in for a chunk (FrameOfModel), quantized as
// the chunk files are, so the one renderer draws both kinds.

import { inflate } from './chunk.js';
import { parsePart } from './model_part.js';
import { ModelDecoder } from './model_decode.js';
import { Stream } from './stream.js';

/** Frames ahead of the playhead whose parts are fetched and kept. */
export const LOOKAHEAD_FRAMES = 24;

const POSITION_STEPS = 65535, LOG_SCALE_STEPS = 255, ROTATION_STEPS = 127, UNIT_STEPS = 255;

/**
 * A decoded frame as the renderer takes a chunk: F = 1, no static part, quantized fields over
 * the kept Gaussians' ranges (atgs/web/stream_format.py's rules), and the floats as decoded.
 */
export class FrameOfModel {
  constructor(decoded) {
    const { count, mean, quat, scale, color } = decoded;
    this.decoded = decoded;
    this.F = 1;
    this.G = count;
    this.S = 0;
    this.D = count;
    const pmin = [Infinity, Infinity, Infinity], pmax = [-Infinity, -Infinity, -Infinity];
    let lo = Infinity, hi = -Infinity;
    for (let i = 0; i < count; i++) {
      if (!(mean[4 * i + 3] > 0)) continue;
      for (let c = 0; c < 3; c++) {
        const x = mean[4 * i + c], l = Math.log(Math.max(scale[4 * i + c], 1e-30));
        if (x < pmin[c]) pmin[c] = x;
        if (x > pmax[c]) pmax[c] = x;
        if (l < lo) lo = l;
        if (l > hi) hi = l;
      }
    }
    if (!(lo <= hi)) { pmin.fill(0); pmax.fill(1); lo = 0; hi = 1; }  // nothing kept
    this.ranges = { posMin: pmin.map(Math.fround), posMax: pmax.map(Math.fround), logScaleMin: Math.fround(lo), logScaleMax: Math.fround(hi) };
    const steps = (x, a, b, n) => Math.min(n, Math.max(0, Math.round(b > a ? ((x - a) / (b - a)) * n : 0)));
    const fields = {
      count, position: new Uint16Array(4 * count), scaleOpacity: new Uint8Array(4 * count),
      rotation: new Int8Array(4 * count), color: new Uint8Array(4 * count), geometryVersion: 0,
    };
    const r = this.ranges;
    for (let i = 0; i < count; i++) {
      const o = mean[4 * i + 3];
      if (!(o > 0)) continue;  // opacity byte 0: the sort and the shader cull it
      for (let c = 0; c < 3; c++) {
        fields.position[4 * i + c] = steps(mean[4 * i + c], r.posMin[c], r.posMax[c], POSITION_STEPS);
        fields.scaleOpacity[4 * i + c] = steps(Math.log(Math.max(scale[4 * i + c], 1e-30)), r.logScaleMin, r.logScaleMax, LOG_SCALE_STEPS);
        fields.color[4 * i + c] = steps(color[4 * i + c], 0, 1, UNIT_STEPS);
      }
      fields.scaleOpacity[4 * i + 3] = steps(o, 0, 1, UNIT_STEPS);
      const q = quat.subarray(4 * i, 4 * i + 4);
      const norm = Math.hypot(q[0], q[1], q[2], q[3]) || 1;
      const sign = q[0] < 0 ? -1 : 1;  // q and -q are one rotation: keep w >= 0
      for (let c = 0; c < 4; c++) fields.rotation[4 * i + c] = Math.round((sign * q[c] / norm) * ROTATION_STEPS);
    }
    this.fields = fields;
  }

  frame(k) {
    if (k !== 0) throw new RangeError(`frame ${k}: a decoded model frame holds frame 0 only`);
    return this.fields;
  }
}

// The failures of the parts a frame needs, as the player reads stream.failed.get(frame).
class FrameFailures {
  constructor(stream) {
    this.stream = stream;
  }

  get(i) {
    if (this.stream.decodeFailure) return this.stream.decodeFailure;
    for (const p of this.stream._partsOf(i)) if (this.stream.partFailed.has(p)) return this.stream.partFailed.get(p);
    return undefined;
  }

  has(i) {
    return this.get(i) !== undefined;
  }
}

export class ModelStream {
  /**
   * @param {string} base folder URL of manifest.json and the parts
   * @param {object} manifest the parsed manifest (kind "model")
   * @param {WebGL2RenderingContext} gl the renderer's context (frames are decoded on it)
   * @param {object} [options] fetch, maxInFlight (2), onProgress(loaded, total), onError(error, part)
   */
  constructor(base, manifest, gl, options = {}) {
    this.base = base.endsWith('/') ? base : `${base}/`;
    this.manifest = manifest;
    this.model = manifest.model;
    this.gl = gl;
    this.maxInFlight = options.maxInFlight ?? 2;
    this.onError = options.onError ?? (() => {});
    this.parts = new Map();       // part index -> its tensors
    this.partFailed = new Map();  // part index -> Error
    this.inFlight = new Set();
    this.waiters = new Map();     // part index -> [{resolve, reject}]
    this.failed = new FrameFailures(this);
    this.decoder = null;
    this.decodeFailure = null;  // the GPU decode's error: no frame decodes after it
    this.decoded = new Map();     // frame -> FrameOfModel (the last two)
    this.playhead = 0;
    // what playing the whole video once downloads: every part once
    this.totalBytes = this.model.parts.reduce((sum, p) => sum + p.bytes, 0);
    this.fetcher = new Stream(base, { fetch: options.fetch, onProgress: options.onProgress });
    this.fetcher.totalBytes = this.totalBytes;
  }

  url(file) {
    return this.base + file;
  }

  /** Units the player steps through: one a frame. */
  get units() {
    return this.manifest.frames.length;
  }

  locate(i) {
    return { chunk: i, local: 0 };
  }

  /** The part indices exported frame i needs: the weights, its anchors, its hash grid. */
  _partsOf(i) {
    const f = this.model.frames[i];
    return [this.model.weights, ...f.anchors, f.hash];
  }

  setPlayhead(i) {
    this.playhead = i;
    this._evict();
    this._pump();
  }

  // The parts of the frames from the playhead on (wrapping: the loop comes back to the start).
  _wanted() {
    const n = this.units, wanted = [];
    for (let k = 0; k < Math.min(n, LOOKAHEAD_FRAMES); k++) {
      for (const p of this._partsOf((this.playhead + k) % n)) if (!wanted.includes(p)) wanted.push(p);
    }
    return wanted;
  }

  // Drops the parts no frame near the playhead needs: memory stays bounded by the look-ahead.
  _evict() {
    const keep = new Set(this._wanted());
    for (const p of this.parts.keys()) if (!keep.has(p)) this.parts.delete(p);
  }

  _pump() {
    for (const p of this._wanted()) {
      if (this.inFlight.size >= this.maxInFlight) return;
      if (this.parts.has(p) || this.inFlight.has(p) || this.partFailed.has(p)) continue;
      this.inFlight.add(p);
      this._download(p).then(
        (tensors) => {
          this.inFlight.delete(p);
          this.parts.set(p, tensors);
          for (const w of this.waiters.get(p) ?? []) w.resolve();
          this.waiters.delete(p);
          this._pump();
        },
        (e) => {
          this.inFlight.delete(p);
          this.partFailed.set(p, e);
          for (const w of this.waiters.get(p) ?? []) w.reject(e);
          this.waiters.delete(p);
          this.onError(e, p);
          this._pump();
        },
      );
    }
  }

  async _download(p) {
    const entry = this.model.parts[p];
    const where = this.url(entry.file);
    // the chunk stream's GET (its errors, its progress count): one way to fetch a file
    const bytes = await this.fetcher._get(where, entry.bytes);
    if (bytes.length !== entry.bytes) {
      throw new Error(`${where} is ${bytes.length < entry.bytes ? 'truncated' : 'longer than the manifest says'} (got ${bytes.length} of ${entry.bytes} bytes)`);
    }
    let inflated;
    try {
      inflated = await inflate(bytes);
    } catch (e) {
      throw new Error(`${where} is corrupt: ${e.message}`);
    }
    return parsePart(inflated, where);
  }

  /** Bytes downloaded so far. */
  get loadedBytes() {
    return this.fetcher.loadedBytes;
  }

  _whenLoaded(p) {
    if (this.parts.has(p)) return Promise.resolve();
    if (this.partFailed.has(p)) return Promise.reject(this.partFailed.get(p));
    return new Promise((resolve, reject) => {
      if (!this.waiters.has(p)) this.waiters.set(p, []);
      this.waiters.get(p).push({ resolve, reject });
      this._pump();
    });
  }

  /** Frame i decoded now if its parts are in (decoding it on the GPU if need be), else null. */
  decodedNow(i) {
    const ready = this.decoded.get(i);
    if (ready) return ready;
    const needed = this._partsOf(i);
    if (!needed.every((p) => this.parts.has(p))) return null;
    if (this.decodeFailure) return null;
    const m = this.model, entry = m.frames[i];
    let frame;
    try {
      if (!this.decoder) this.decoder = new ModelDecoder(this.gl, m, this.parts.get(m.weights));
      this.decoder.setAnchors(entry.anchors.join(','), entry.anchors.map((p) => ({ keyframe: m.parts[p].keyframe, tensors: this.parts.get(p) })));
      this.decoder.setHash(String(entry.hash), this.parts.get(entry.hash));
      frame = new FrameOfModel(this.decoder.decode(entry));
    } catch (e) {  // no float targets, a shader the GPU refuses: every frame fails the same way
      this.decodeFailure = e;
      this.onError(e, i);
      return null;
    }
    this.decoded.set(i, frame);
    while (this.decoded.size > 2) this.decoded.delete(this.decoded.keys().next().value);
    return frame;
  }

  /** Frame i decoded, once its parts are in. */
  async chunk(i) {
    const failure = this.failed.get(i);
    if (failure) throw failure;
    await Promise.all(this._partsOf(i).map((p) => this._whenLoaded(p)));
    return this.decodedNow(i);
  }

  /**
   * The Gaussians of frame i as decoded (for tests): per slot, mean + opacity, rotation, scale +
   * kept and colour (4 floats each), and the anchor parts in the page's order.
   */
  async gaussians(i) {
    const frame = await this.chunk(i);
    const d = frame.decoded, n = 4 * d.count;
    const plain = (a) => Array.from(a.subarray(0, n));
    return { count: d.count, anchors: this.model.frames[i].anchors, mean: plain(d.mean), quat: plain(d.quat),
      scale: plain(d.scale), color: plain(d.color) };
  }
}
