// A model stream (manifest kind "model", docs/web.md "Streaming the model"): the part files the
// frames from the playhead on need, held in a window.js FetchWindow within the page's byte budget
// and fetched through fetcher.js (stall timeout, retries), and each frame decoded on the GPU
// (model_decode.js) when the player asks for it. Offers the player the interface of stream.js
// (streams.js) with one frame a unit. What it hands the renderer is a one-frame frame source
// (DecodedFrame) holding the decode's float read-backs as they are, drawn by the one renderer
// through its float layout (frame_layouts.js): no quantization on the model stream's path.

import { inflate } from './chunk.js';
import { StreamFolder } from './fetcher.js';
import { parsePart } from './model_part.js';
import { ModelDecoder } from './model_decode.js';
import { DEFAULT_BUDGET_BYTES, FetchWindow, playingOrder } from './window.js';

/** Bytes a decoded frame holds a Gaussian slot: the four RGBA float32 read-backs of the decode. */
export const DECODED_BYTES_PER_SLOT = 64;

/**
 * A decoded frame as the renderer takes a frame source (renderer.js draw): F = 1, no static
 * part, and the decode's float32 read-backs themselves as its fields (layout "float",
 * frame_layouts.js: drawn as decoded, no quantization; a dropped Gaussian has opacity 0, which
 * the sort and the shader cull).
 */
export class DecodedFrame {
  constructor(decoded) {
    const { count, mean, quat, scale, color } = decoded;
    this.decoded = decoded;
    this.layout = 'float';
    this.F = 1;
    this.G = count;
    this.S = 0;
    this.D = count;
    // position and opacity: what the depth sort reads (x, y, z and the opacity of each mean texel)
    this.fields = { count, mean, quat, scale, color, position: mean, opacity: mean, geometryVersion: 0 };
  }

  frame(k) {
    if (k !== 0) throw new RangeError(`frame ${k}: a decoded model frame holds frame 0 only`);
    return this.fields;
  }
}

/**
 * The loader of a model stream. The window's items are the part files, each counted at what it
 * holds once read (its `values` as float32: parts are kept parsed, since a frame is decoded at
 * once when asked for); its order from a playhead frame is the parts of that frame, then the new
 * ones of each next frame (past the last back to the first while looping), so a part many frames
 * share (the weights, a keyframe's anchors, a segment's grid) is held once, from the first of
 * them to the last. Fetches nothing until setPlayhead.
 */
export class ModelStream {
  /**
   * @param {string} base folder URL of manifest.json and the parts
   * @param {object} manifest the parsed manifest (kind "model", streams.js checkModelManifest)
   * @param {WebGL2RenderingContext} gl the renderer's context (frames are decoded on it)
   * @param {object} [options] stream.js Stream's: fetch and fetcher.js's settings, budgetBytes
   *   (raised to what the playing frame and the next need: minimumBytes), maxChunks (parts held
   *   at most, raised to the playing frame's and the next's), wrap, maxInFlight (2), onProgress,
   *   onRetry, onChunkLoaded(part), onError(error, part, retryAt) for a part's failure (stream.js's
   *   rule) and onError(error) for the GPU decode's (every frame decodes alike: nothing plays),
   *   retryDelayMs, maxRetryDelayMs, clock
   */
  constructor(base, manifest, gl, options = {}) {
    this.folder = new StreamFolder(base, options);
    this.options = options;
    this.manifest = manifest;
    this.model = manifest.model;
    this.gl = gl;
    this.maxDecoded = 2;
    this.onProgress = options.onProgress ?? (() => {});
    this.onError = options.onError ?? (() => {});
    this.onChunkLoaded = options.onChunkLoaded ?? (() => {});
    this.decoder = null;
    this.decodeFailure = null;  // the GPU decode's error: no frame decodes after it
    // the last frame decoded: {frame, decodeMs (the GPU passes and the read-back), prepareMs (the
    // frame object the renderer takes)}; state() carries it for bench/web.py
    this.lastDecode = null;
    this.decoded = new Map();   // frame -> DecodedFrame, in least-recently-used order
    this.playhead = 0;
    this.fetchedBytes = 0;
    // what playing the whole video once downloads: every part once
    this.totalBytes = this.model.parts.reduce((sum, p) => sum + p.bytes, 0);
    const sizes = this.model.parts.map((p) => 4 * p.values);
    const slots = (f) => this.model.frames[f].anchors.reduce((n, p) => n + this.model.parts[p].anchors, 0) * this.model.q;
    this.decodedReserve = (this.maxDecoded + 1) * DECODED_BYTES_PER_SLOT * Math.max(...this.model.frames.map((_, f) => slots(f)));
    // the least that plays without a stall: the playing frame's parts and the next's, and the decoded frames
    let minimumParts = 0, minimumHeld = 0;
    for (let f = 0; f < this.units; f++) {
      const both = new Set([...this._partsOf(f), ...this._partsOf((f + 1) % this.units)]);
      minimumParts = Math.max(minimumParts, both.size);
      minimumHeld = Math.max(minimumHeld, [...both].reduce((sum, p) => sum + sizes[p], 0));
    }
    this.minimumBytes = this.decodedReserve + minimumHeld;
    this.budgetBytes = Math.max(options.budgetBytes ?? DEFAULT_BUDGET_BYTES, this.minimumBytes);
    this.window = new FetchWindow({
      sizes,
      load: (p, signal) => this._download(p, signal),
      budgetBytes: this.budgetBytes - this.decodedReserve,
      maxItems: Math.max(options.maxChunks ?? Infinity, minimumParts),
      maxInFlight: options.maxInFlight ?? 2,
      wrap: options.wrap ?? true,
      order: (frame, wrap) => this._order(frame, wrap),
      onLoaded: (p) => { this.onChunkLoaded(p); this._progress(); },
      onFailed: (p, e, retryAt) => this.onError(e, p, retryAt),
      retryDelayMs: options.retryDelayMs,
      maxRetryDelayMs: options.maxRetryDelayMs,
      clock: options.clock,
    });
  }

  url(file) {
    return this.folder.url(file);
  }

  /** Fetch a file of the stream folder with the stream's timeout and retries (the environment map). */
  fetchFile(file, extra = {}) {
    return this.folder.get(file, extra);
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

  // The window's order from playhead frame `frame`: each frame's parts not listed for an earlier one.
  * _order(frame, wrap) {
    const listed = new Set();
    for (const f of playingOrder(frame, wrap, this.units)) {
      for (const p of this._partsOf(f)) {
        if (listed.has(p)) continue;
        listed.add(p);
        yield p;
      }
      if (listed.size === this.model.parts.length) return;
    }
  }

  /**
   * Move the window to start at frame i: parts no frame from there on needs within the budget
   * are dropped. `asked`: the viewer asked for frame i (a seek, Play): the failures of its parts
   * no longer stand and they are fetched again now.
   */
  setPlayhead(i, asked = false) {
    this.playhead = i;
    this.window.setPlayhead(i);
    if (asked) for (const p of this._partsOf(i)) if (this.window.failure(p)) this.window.forget(p);
    this._progress();
  }

  /**
   * The failure that keeps frame i from decoding while it stands, else undefined: {error,
   * retryAt} (stream.js Stream.failure), the GPU decode's (for good) before any part's, and of
   * its parts' the one that stands longest.
   */
  failure(i) {
    if (this.decodeFailure) return { error: this.decodeFailure, retryAt: Infinity };
    let worst;
    for (const p of this._partsOf(i)) {
      const f = this.window.failure(p);
      if (f && !(worst?.retryAt >= f.retryAt)) worst = f;
    }
    return worst;
  }

  /** Whether the window continues at frame 0 past the last one (the page's loop box). */
  setWrap(wrap) {
    this.options.wrap = wrap;
    this.window.setWrap(wrap);
  }

  /** The renderer's context came back: the decoder's textures and programs were on the lost one. */
  contextRestored() {
    this.decoder = null;
  }

  /** Abort the downloads and drop the parts. */
  close() {
    this.window.close();
    this.decoded.clear();
  }

  /** What the stream holds now (stream.js Stream.memory's fields; its "chunks" are parts here). */
  memory() {
    return {
      ...this.window.memory(), budgetBytes: this.budgetBytes, minimumBytes: this.minimumBytes,
      decodedReserveBytes: this.decodedReserve, decodedChunks: this.decoded.size, fetchedBytes: this.fetchedBytes,
      lastDecode: this.lastDecode,
    };
  }

  async _download(p, signal) {
    const entry = this.model.parts[p];
    const bytes = await this.folder.getSized(entry.file, entry.bytes, { signal, onBytes: (n) => { this.fetchedBytes += n; } });
    const where = this.url(entry.file);
    let inflated;
    try {
      inflated = await inflate(bytes);
    } catch (e) {
      throw new Error(`${where} is corrupt: ${e.message}`);
    }
    return parsePart(inflated, where);
  }

  _progress() {
    this.onProgress(...this.window.progress());
  }

  /** Frame i decoded now if its parts are in (decoding it on the GPU if need be), else null. */
  decodedNow(i) {
    const ready = this.decoded.get(i);
    if (ready) {
      this.decoded.delete(i);  // most recently used goes last
      this.decoded.set(i, ready);
      return ready;
    }
    const w = this.window;
    if (this.decodeFailure || !this._partsOf(i).every((p) => w.peek(p) !== undefined)) return null;
    const m = this.model, entry = m.frames[i];
    let frame;
    try {
      const t0 = performance.now();
      if (!this.decoder) this.decoder = new ModelDecoder(this.gl, m, w.peek(m.weights));
      this.decoder.setAnchors(entry.anchors.join(','), entry.anchors.map((p) => ({ keyframe: m.parts[p].keyframe, tensors: w.peek(p) })));
      this.decoder.setHash(String(entry.hash), w.peek(entry.hash));
      const decoded = this.decoder.decode(entry);  // readPixels waits for the GPU: the passes are in this time
      const t1 = performance.now();
      frame = new DecodedFrame(decoded);
      this.lastDecode = { frame: i, decodeMs: t1 - t0, prepareMs: performance.now() - t1 };
    } catch (e) {  // no float targets, a shader the GPU refuses: every frame fails the same way
      this.decodeFailure = e;
      this.onError(e);
      return null;
    }
    this.decoded.set(i, frame);
    while (this.decoded.size > this.maxDecoded) this.decoded.delete(this.decoded.keys().next().value);
    return frame;
  }

  /**
   * Frame i decoded, once its parts are in; waits for them (a frame outside the window waits
   * until setPlayhead brings its parts in).
   */
  async chunk(i) {
    for (;;) {
      const failure = this.failure(i);
      if (failure) throw failure.error;
      const frame = this.decodedNow(i);
      if (frame) return frame;
      if (this.decodeFailure) throw this.decodeFailure;
      await Promise.all(this._partsOf(i).map((p) => this.window.get(p)));
    }
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
