// The stream folder of a web export (docs/web.md): manifest.json, then the chunk files in
// playing order, at most two requests at a time, the chunk a seek needs first. Compressed bytes
// of every loaded chunk are kept (a seek back costs an inflate, not a download); decoded chunks
// only for the few most recently used. No DOM: Node tests it with a stand-in fetch.

import { inflate, parseChunk } from './chunk.js';

export const FORMAT = 'atgs-web';
export const VERSION = 1;

/**
 * Checks the manifest's fields the player relies on; throws one line naming the first problem.
 * @param {object} m parsed manifest.json
 * @param {string} where the manifest's URL, for the message
 */
export function checkManifest(m, where) {
  const fail = (what) => { throw new Error(`${where}: ${what}`); };
  if (!m || typeof m !== 'object') fail('not a JSON object');
  if (m.format !== FORMAT) fail(`format is ${JSON.stringify(m.format)}, not "${FORMAT}"`);
  if (m.version !== VERSION) fail(`version ${m.version} is not supported (this player reads version ${VERSION})`);
  if (!Array.isArray(m.frames) || m.frames.length === 0) fail('"frames" is empty');
  if (!(m.fps > 0)) fail(`fps ${m.fps} is not a positive number`);
  const F = m.chunk_frames;
  if (!Number.isInteger(F) || F < 1) fail(`chunk_frames ${F} is not a positive integer`);
  const n = Math.ceil(m.frames.length / F);
  if (!Array.isArray(m.chunks) || m.chunks.length !== n) {
    fail(`${m.frames.length} frames in chunks of ${F} need ${n} chunks, the manifest lists ${m.chunks?.length ?? 0}`);
  }
  m.chunks.forEach((c, i) => {
    const frames = Math.min(F, m.frames.length - i * F);
    if (typeof c.file !== 'string' || !c.file) fail(`chunk ${i} has no file name`);
    if (c.frames !== frames) fail(`${c.file} holds ${c.frames} frames, ${frames} expected`);
    if (!Number.isInteger(c.bytes) || c.bytes <= 0) fail(`${c.file} has no byte size`);
  });
  if (!Array.isArray(m.cameras)) fail('"cameras" is missing');
  for (const key of ['near', 'dilation', 'alpha_min', 'alpha_max', 'extent']) {
    if (typeof m.render?.[key] !== 'number') fail(`render.${key} is missing`);
  }
}

/**
 * The loader of one exported stream.
 * Callbacks (all optional): onProgress(loadedBytes, totalBytes); onChunkLoaded(index);
 * onError(error, index) for each failure: the manifest's (index undefined: nothing loads after
 * it) or chunk index's (missing, truncated, corrupt: that chunk stays failed, every request for
 * it rejects with the same error, and the other chunks load on).
 */
export class Stream {
  /**
   * @param {string} base folder URL of manifest.json and the chunks ("stream/")
   * @param {object} [options]
   * @param {typeof fetch} [options.fetch] the fetch to use (tests pass a stand-in)
   * @param {number} [options.maxInFlight] concurrent chunk requests (2)
   * @param {number} [options.maxDecoded] decoded chunks kept (3)
   */
  constructor(base = 'stream/', options = {}) {
    this.base = base.endsWith('/') ? base : `${base}/`;
    this.fetch = options.fetch ?? ((url) => globalThis.fetch(url));
    this.maxInFlight = options.maxInFlight ?? 2;
    this.maxDecoded = options.maxDecoded ?? 3;
    this.onProgress = options.onProgress ?? (() => {});
    this.onError = options.onError ?? (() => {});
    this.onChunkLoaded = options.onChunkLoaded ?? (() => {});
    this.manifest = null;
    this.failed = new Map();   // chunk index -> its Error
    this.loadedBytes = 0;
    this.totalBytes = 0;
    this.compressed = [];      // chunk index -> Uint8Array of the file
    this.inFlight = new Set();
    this.waiters = new Map();  // chunk index -> [{resolve, reject}]
    this.decoded = new Map();  // chunk index -> Chunk, in least-recently-used order
    this.decoding = new Map(); // chunk index -> Promise<Chunk>
    this.playhead = 0;
  }

  /** Units the player steps through (streams.js's interface): the chunks. */
  get units() {
    return this.manifest.chunks.length;
  }

  /** URL of a file of the stream folder. */
  url(file) {
    return this.base + file;
  }

  /** Loads and checks manifest.json, then starts loading chunks. @returns {Promise<object>} the manifest */
  async open() {
    const where = this.url('manifest.json');
    try {
      const bytes = await this._get(where, null);
      let manifest;
      try {
        manifest = JSON.parse(new TextDecoder().decode(bytes));
      } catch (e) {
        throw new Error(`${where} is not valid JSON (${e.message})`);
      }
      checkManifest(manifest, where);
      this.manifest = manifest;
      this.totalBytes = manifest.chunks.reduce((sum, c) => sum + c.bytes, 0);
      this.onProgress(this.loadedBytes, this.totalBytes);
      this._pump();
      return manifest;
    } catch (e) {
      this.onError(e, undefined);
      throw e;
    }
  }

  /** {chunk, local}: the chunk that holds exported frame i and the frame's index in it. */
  locate(i) {
    const F = this.manifest.chunk_frames;
    return { chunk: Math.floor(i / F), local: i % F };
  }

  /**
   * Load chunk i next (if it is not loaded), then the ones after it in order (wrapping around).
   * The player calls it with the chunk it plays or seeks to.
   */
  setPlayhead(i) {
    this.playhead = i;
    this._pump();
  }

  /** True once chunk i's file is downloaded and checked. */
  isLoaded(i) {
    return this.compressed[i] !== undefined;
  }

  /** Chunk i decoded, if it is in the decoded cache now (no waiting), else null. */
  decodedNow(i) {
    const chunk = this.decoded.get(i);
    if (!chunk) return null;
    this.decoded.delete(i);  // most recently used goes last
    this.decoded.set(i, chunk);
    return chunk;
  }

  /**
   * Chunk i inflated, parsed and checked against the manifest; waits for its download
   * (without moving it ahead of others: call setPlayhead for that).
   * @returns {Promise<import('./chunk.js').Chunk>}
   */
  chunk(i) {
    const ready = this.decodedNow(i);
    if (ready) return Promise.resolve(ready);
    if (this.failed.has(i)) return Promise.reject(this.failed.get(i));
    if (!this.decoding.has(i)) {
      const job = this._decode(i).finally(() => this.decoding.delete(i));
      job.catch(() => {});  // failures are reported through onError and the returned promise
      this.decoding.set(i, job);
    }
    return this.decoding.get(i);
  }

  async _decode(i) {
    await this._whenLoaded(i);
    const entry = this.manifest.chunks[i];
    const where = this.url(entry.file);
    let chunk;
    try {
      chunk = parseChunk(await inflate(this.compressed[i]));
    } catch (e) {
      throw this._failChunk(i, new Error(`${where} is corrupt: ${e.message}`));
    }
    const expected = { F: entry.frames, G: entry.gaussians, S: entry.static };
    for (const [key, value] of Object.entries(expected)) {
      if (value !== undefined && chunk[key] !== value) {
        throw this._failChunk(i, new Error(`${where} does not match the manifest: ${key} = ${chunk[key]}, the manifest says ${value}`));
      }
    }
    this.decoded.set(i, chunk);
    while (this.decoded.size > this.maxDecoded) this.decoded.delete(this.decoded.keys().next().value);
    return chunk;
  }

  _whenLoaded(i) {
    if (this.isLoaded(i)) return Promise.resolve();
    if (this.failed.has(i)) return Promise.reject(this.failed.get(i));
    return new Promise((resolve, reject) => {
      if (!this.waiters.has(i)) this.waiters.set(i, []);
      this.waiters.get(i).push({ resolve, reject });
      this._pump();
    });
  }

  // The next chunk to request: the first not loaded, in flight nor failed from the playhead on, wrapping.
  _next() {
    const n = this.manifest.chunks.length;
    for (let j = 0; j < n; j++) {
      const i = (this.playhead + j) % n;
      if (!this.isLoaded(i) && !this.inFlight.has(i) && !this.failed.has(i)) return i;
    }
    return -1;
  }

  _pump() {
    if (!this.manifest) return;
    while (this.inFlight.size < this.maxInFlight) {
      const i = this._next();
      if (i < 0) return;
      this.inFlight.add(i);
      this._download(i).then(
        () => {
          this.inFlight.delete(i);
          this.onChunkLoaded(i);
          for (const w of this.waiters.get(i) ?? []) w.resolve();
          this.waiters.delete(i);
          this._pump();
        },
        (e) => {
          this.inFlight.delete(i);
          this._failChunk(i, e);
          this._pump();
        },
      );
    }
  }

  async _download(i) {
    const entry = this.manifest.chunks[i];
    const where = this.url(entry.file);
    const bytes = await this._get(where, entry.bytes);
    if (bytes.length < entry.bytes) throw new Error(`${where} is truncated (got ${bytes.length} of ${entry.bytes} bytes)`);
    if (bytes.length > entry.bytes) throw new Error(`${where} is ${bytes.length} bytes, the manifest says ${entry.bytes}`);
    this.compressed[i] = bytes;
  }

  // GET url and return its body; with `expected` (bytes), count the body into loadedBytes as it arrives.
  async _get(where, expected) {
    let response;
    try {
      response = await this.fetch(where);
    } catch (e) {
      throw new Error(`could not fetch ${where} (${e.message})`);
    }
    if (response.status === 404) throw new Error(`${where} is missing (HTTP 404)`);
    if (!response.ok) throw new Error(`${where} could not be loaded (HTTP ${response.status})`);
    if (expected === null || !response.body) {
      const bytes = new Uint8Array(await response.arrayBuffer());
      if (expected !== null) this._count(Math.min(bytes.length, expected));
      return bytes;
    }
    const parts = [];
    let got = 0;
    const reader = response.body.getReader();
    for (;;) {
      const { done, value } = await reader.read();
      if (done) break;
      parts.push(value);
      // progress never passes the manifest's size, whatever arrives
      this._count(Math.max(0, Math.min(value.length, expected - got)));
      got += value.length;
    }
    const bytes = new Uint8Array(got);
    let offset = 0;
    for (const p of parts) {
      bytes.set(p, offset);
      offset += p.length;
    }
    return bytes;
  }

  _count(n) {
    if (n <= 0) return;
    this.loadedBytes += n;
    this.onProgress(this.loadedBytes, this.totalBytes);
  }

  // Marks chunk i failed (its first error stands), rejects its waiters, reports it once; returns the error.
  _failChunk(i, error) {
    if (this.failed.has(i)) return this.failed.get(i);
    this.failed.set(i, error);
    for (const w of this.waiters.get(i) ?? []) w.reject(error);
    this.waiters.delete(i);
    this.onError(error, i);
    return error;
  }
}
