// The stream folder of a web export (docs/web.md): manifest.json, then the chunk files through a
// FetchWindow (window.js): a look-ahead window from the playhead's chunk on, within a byte budget,
// at most two requests at a time, fetched with a stall timeout and retries (fetcher.js). Chunks
// behind the playhead are dropped, and a seek outside the window fetches again; decoded chunks
// are kept only for the few most recently used. No DOM: Node tests it with a stand-in fetch.

import { HEADER_BYTES, RECORD_BYTES, inflate, parseChunk } from './chunk.js';
import { StreamFolder } from './fetcher.js';
import { DEFAULT_BUDGET_BYTES, FetchWindow } from './window.js';

export const FORMAT = 'atgs-web';
export const VERSION = 1;

/**
 * Checks the fields every stream kind's manifest has (format, version, frames, fps, cameras,
 * render); throws one line naming the first problem.
 * @param {object} m parsed manifest.json
 * @param {string} where the manifest's URL, for the message
 */
export function checkCommonManifest(m, where) {
  const fail = (what) => { throw new Error(`${where}: ${what}`); };
  if (!m || typeof m !== 'object') fail('not a JSON object');
  if (m.format !== FORMAT) fail(`format is ${JSON.stringify(m.format)}, not "${FORMAT}"`);
  if (m.version !== VERSION) fail(`version ${m.version} is not supported (this player reads version ${VERSION})`);
  if (!Array.isArray(m.frames) || m.frames.length === 0) fail('"frames" is empty');
  if (!(m.fps > 0)) fail(`fps ${m.fps} is not a positive number`);
  if (!Array.isArray(m.cameras)) fail('"cameras" is missing');
  for (const key of ['near', 'dilation', 'alpha_min', 'alpha_max', 'extent']) {
    if (typeof m.render?.[key] !== 'number') fail(`render.${key} is missing`);
  }
}

/**
 * Checks a chunk stream's manifest (checkCommonManifest, then its chunks); throws one line naming
 * the first problem.
 */
export function checkManifest(m, where) {
  checkCommonManifest(m, where);
  const fail = (what) => { throw new Error(`${where}: ${what}`); };
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
}

/**
 * A stream folder's manifest.json, fetched (timeout, retries) and parsed; throws one line.
 * @param {StreamFolder} folder
 */
export async function readManifest(folder) {
  const bytes = await folder.get('manifest.json');
  try {
    return JSON.parse(new TextDecoder().decode(bytes));
  } catch (e) {
    throw new Error(`${folder.url('manifest.json')} is not valid JSON (${e.message})`);
  }
}

/**
 * A chunk's inflated size from the manifest's entry (docs/web.md, "A chunk file"); 0 if the entry
 * lacks the Gaussian counts.
 * @param {{frames: number, gaussians?: number, static?: number}} entry the manifest's chunk entry
 */
export function inflatedBytes(entry) {
  if (entry.gaussians === undefined) return 0;
  const G = entry.gaussians, S = entry.static ?? 0;
  return HEADER_BYTES + RECORD_BYTES * (S + entry.frames * (G - S));
}

/**
 * Bytes a decoded chunk holds (chunk.js Chunk): its inflated file, the running state of its
 * dynamic block and the four field arrays of a frame.
 */
export function decodedBytes(entry) {
  const G = entry.gaussians ?? 0, D = G - (entry.static ?? 0);
  return inflatedBytes(entry) + RECORD_BYTES * D + 16 * G;
}

/**
 * The loader of one exported stream.
 * Callbacks (all optional): onProgress(bufferedBytes, windowBytes): the window's bytes held of
 * those it wants; onChunkLoaded(index); onRetry(file, attempt, delayMs, error) before a retry;
 * onError(error, index, retryAt) for each failure: the manifest's (index undefined: nothing loads
 * after it) or chunk index's once its retries are spent (every request for it rejects with that
 * error while it stands, and the other chunks load on). retryAt: when it is fetched again unasked
 * (performance.now() time: after an outage's network error, stall or 5xx, retry.js), or Infinity
 * (missing, truncated, corrupt: only once asked for, setPlayhead(index, true)).
 */
export class Stream {
  /**
   * @param {string} base folder URL of manifest.json and the chunks ("stream/")
   * @param {object} [options]
   * @param {typeof fetch} [options.fetch] the fetch to use (tests pass a stand-in)
   * @param {number} [options.budgetBytes] bytes of chunks held at most (window.js DEFAULT_BUDGET_BYTES):
   *   the decoded chunks' share (maxDecoded of the largest, and one being inflated) first, the rest for the compressed
   *   window; raised to what playing without a stall at every chunk needs (minimumBytes: the
   *   decoded share and two compressed chunks, the playing one and the next)
   * @param {number} [options.maxChunks] chunks held at most (no limit)
   * @param {boolean} [options.wrap] the window continues at chunk 0 past the last (true: the page loops by default)
   * @param {number} [options.maxInFlight] concurrent chunk requests (2)
   * @param {number} [options.maxDecoded] decoded chunks kept (2: the one playing and the next; a decoded
   *   chunk holds about 17 bytes a Gaussian a frame, several times its compressed size)
   * @param {number} [options.timeoutMs], [options.retries], [options.backoffMs], [options.maxBackoffMs]
   *   fetcher.js FETCH_DEFAULTS; [options.random], [options.sleep]: its jitter and wait (tests)
   * @param {number} [options.retryDelayMs], [options.maxRetryDelayMs] the waits before a failed chunk
   *   is fetched again unasked (retry.js RETRY_LATER_DEFAULTS); [options.clock]: their clock (tests)
   */
  constructor(base = 'stream/', options = {}) {
    this.folder = new StreamFolder(base, options);
    this.options = options;
    this.maxDecoded = options.maxDecoded ?? 2;
    this.onProgress = options.onProgress ?? (() => {});
    this.onError = options.onError ?? (() => {});
    this.onChunkLoaded = options.onChunkLoaded ?? (() => {});
    this.manifest = null;
    this.window = null;        // FetchWindow over the chunk files, once the manifest is in
    this.broken = new Map();   // chunk index -> its decode Error (downloaded, but corrupt): until asked for again
    this.fetchedBytes = 0;     // chunk body bytes received, every attempt and every refetch counted
    this.totalBytes = 0;       // the chunk files' total size
    this.decoded = new Map();  // chunk index -> Chunk, in least-recently-used order
    this.decoding = new Map(); // chunk index -> Promise<Chunk>
    this.playhead = 0;
    this.budgetBytes = null;   // once open: the budget in force (options.budgetBytes, or raised to minimumBytes)
    this.minimumBytes = null;
  }

  /** Units the player steps through (streams.js's interface): the chunks. */
  get units() {
    return this.manifest.chunks.length;
  }

  /** URL of a file of the stream folder. */
  url(file) {
    return this.folder.url(file);
  }

  /** Fetch a file of the stream folder with the stream's timeout and retries (the environment map too). */
  fetchFile(file, extra = {}) {
    return this.folder.get(file, extra);
  }

  /**
   * Loads and checks manifest.json (or takes the one streams.js read), then starts loading chunks.
   * @param {object} [read] the manifest, already fetched and parsed
   * @returns {Promise<object>} the manifest
   */
  async open(read = undefined) {
    const where = this.url('manifest.json');
    try {
      const manifest = read ?? await readManifest(this.folder);
      checkManifest(manifest, where);
      this.manifest = manifest;
      this.totalBytes = manifest.chunks.reduce((sum, c) => sum + c.bytes, 0);
      this.decodedReserve = (this.maxDecoded + 1) * Math.max(...manifest.chunks.map(decodedBytes));
      const largest = [...manifest.chunks.map((c) => c.bytes)].sort((a, b) => b - a);
      this.minimumBytes = this.decodedReserve + largest[0] + (largest[1] ?? 0);
      this.budgetBytes = Math.max(this.options.budgetBytes ?? DEFAULT_BUDGET_BYTES, this.minimumBytes);
      this.window = new FetchWindow({
        sizes: manifest.chunks.map((c) => c.bytes),
        load: (i, signal) => this._download(i, signal),
        budgetBytes: Math.max(0, this.budgetBytes - this.decodedReserve),
        maxItems: this.options.maxChunks,
        maxInFlight: this.options.maxInFlight ?? 2,
        wrap: this.options.wrap ?? true,
        onLoaded: (i) => { this.onChunkLoaded(i); this._progress(); },
        onFailed: (i, e, retryAt) => this.onError(e, i, retryAt),
        retryDelayMs: this.options.retryDelayMs,
        maxRetryDelayMs: this.options.maxRetryDelayMs,
        clock: this.options.clock,
      });
      this.window.setPlayhead(this.playhead);
      this._progress();
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
   * Move the window to start at chunk i: chunks outside it are dropped and their downloads
   * aborted, then chunk i is fetched first (if it is not held), and the ones after it in order.
   * The player calls it with the chunk it plays or seeks to; `asked`: the viewer asked for it (a
   * seek, Play): a failure of chunk i no longer stands and it is fetched again now.
   */
  setPlayhead(i, asked = false) {
    this.playhead = i;
    if (!this.window) return;
    this.window.setPlayhead(i);
    if (asked && (this.broken.delete(i) || this.window.failure(i))) this.window.forget(i);
    this._progress();
  }

  /**
   * Chunk i's failure while it stands, else undefined: {error, retryAt} (retryAt: when it is
   * fetched again unasked, Infinity: only once asked for).
   */
  failure(i) {
    const broken = this.broken.get(i);
    if (broken) return { error: broken, retryAt: Infinity };
    return this.window?.failure(i);
  }

  /** Whether the window continues at chunk 0 past the last one (the page's loop box). */
  setWrap(wrap) {
    this.options.wrap = wrap;
    this.window?.setWrap(wrap);
  }

  /** The renderer's context came back (streams.js's interface): a chunk stream holds nothing on the GPU. */
  contextRestored() {}

  /** Abort the downloads and drop the chunks (a page that stops playing for good). */
  close() {
    this.window?.close();
    this.decoded.clear();
  }

  /** True while chunk i's file is held (downloaded, checked, not evicted). */
  isLoaded(i) {
    return this.window?.peek(i) !== undefined;
  }

  /**
   * What the stream holds now: compressed bytes and chunks (in flight included), the peaks since
   * opening, the budget in force, the least it may be (minimumBytes), its part for the compressed
   * window (the rest is the decoded chunks' reserve), bytes fetched, downloads started, and whether the window is complete.
   */
  memory() {
    const w = this.window;
    return {
      heldBytes: 0, heldChunks: 0, peakHeldBytes: 0, peakHeldChunks: 0, windowBudgetBytes: null,
      maxChunks: this.options.maxChunks ?? Infinity, downloads: 0, windowFull: false, ...w?.memory(),
      budgetBytes: this.budgetBytes ?? (this.options.budgetBytes ?? DEFAULT_BUDGET_BYTES),
      minimumBytes: this.minimumBytes ?? null, decodedReserveBytes: w ? this.decodedReserve : null,
      decodedChunks: this.decoded.size, fetchedBytes: this.fetchedBytes,
    };
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
   * Chunk i inflated, parsed and checked against the manifest; waits for its download (a chunk
   * outside the window waits until setPlayhead brings it in).
   * @returns {Promise<import('./chunk.js').Chunk>}
   */
  chunk(i) {
    const ready = this.decodedNow(i);
    if (ready) return Promise.resolve(ready);
    const failure = this.failure(i);
    if (failure) return Promise.reject(failure.error);
    if (!this.decoding.has(i)) {
      const job = this._decode(i).finally(() => this.decoding.delete(i));
      job.catch(() => {});  // failures are reported through onError and the returned promise
      this.decoding.set(i, job);
    }
    return this.decoding.get(i);
  }

  async _decode(i) {
    const bytes = await this._whenLoaded(i);
    const entry = this.manifest.chunks[i];
    const where = this.url(entry.file);
    let chunk;
    try {
      chunk = parseChunk(await inflate(bytes, inflatedBytes(entry)));
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
    if (!this.window) return Promise.reject(new Error('the stream is not open'));
    return this.window.get(i);
  }

  _download(i, signal) {
    const entry = this.manifest.chunks[i];
    return this.folder.getSized(entry.file, entry.bytes, { signal, onBytes: (n) => { this.fetchedBytes += n; } });
  }

  _progress() {
    this.onProgress(...this.window.progress());
  }

  // Marks chunk i broken (its first error stands until it is asked for again), reports it once; returns the error.
  _failChunk(i, error) {
    if (this.broken.has(i)) return this.broken.get(i);
    this.broken.set(i, error);
    this.onError(error, i, Infinity);
    return error;
  }
}
