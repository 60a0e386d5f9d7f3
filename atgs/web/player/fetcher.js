// One HTTP GET of a stream file with the failure handling a real connection needs: a stall
// timeout (no headers or no body bytes for timeoutMs aborts the attempt), retries of the
// failures that may pass (network errors, stalls, HTTP 408/429/5xx) after an exponential
// back-off with jitter, and an abort signal for a caller that no longer wants the bytes (a seek,
// an eviction). Every stream kind fetches through here (docs/web.md, "Streaming"). No DOM:
// Node tests it with a stand-in fetch and clock.

import { readAll } from './read.js';

/** The defaults (docs/web.md): 15 s without a byte is a stall; 4 retries after 0.5, 1, 2, 4 s (x 0.5..1 jitter). */
export const FETCH_DEFAULTS = Object.freeze({ timeoutMs: 15000, retries: 4, backoffMs: 500, maxBackoffMs: 8000 });

/** A failure of fetchBytes; `retryable`: whether another attempt might succeed. */
export class FetchError extends Error {
  constructor(message, retryable) {
    super(message);
    this.name = 'FetchError';
    this.retryable = retryable;
  }
}

/** True for the rejection of a fetch the caller aborted (not a failure to report). */
export function isAbort(error) {
  return error?.name === 'AbortError';
}

function abortError() {
  return new DOMException('the fetch was aborted', 'AbortError');
}

/**
 * The wait before retry `attempt` (0: the first retry): backoffMs 2^attempt, at most
 * maxBackoffMs, times a random factor in [0.5, 1) so that many viewers of one server do not
 * retry in step.
 */
export function backoffDelay(attempt, { backoffMs, maxBackoffMs }, random = Math.random) {
  return Math.min(maxBackoffMs, backoffMs * 2 ** attempt) * (0.5 + 0.5 * random());
}

// HTTP statuses a later attempt may not get: a timeout, rate limiting, the server's own failures.
function retryableStatus(status) {
  return status === 408 || status === 429 || status >= 500;
}

/**
 * GET `url`'s body.
 * @param {string} url
 * @param {object} [options] FETCH_DEFAULTS' fields, and:
 * @param {typeof fetch} [options.fetch] the fetch (fetch(url, {signal}))
 * @param {AbortSignal} [options.signal] aborts every attempt and the waits: rejects with an AbortError
 * @param {(n: number) => void} [options.onBytes] body bytes as they arrive (every attempt's: network bytes)
 * @param {number} [options.expectedBytes] the body's size if known (read into one buffer of that size)
 * @param {(attempt: number, delayMs: number, error: FetchError) => void} [options.onRetry] before each retry's wait
 * @param {() => number} [options.random] for the jitter (tests)
 * @param {(ms: number, signal?: AbortSignal) => Promise<void>} [options.sleep] the back-off wait (tests)
 * @returns {Promise<Uint8Array>}
 * @throws {FetchError} one line naming the file: "... is missing (HTTP 404)", "... could not be
 *   loaded (HTTP 500, 5 tries)", "could not fetch ... (reason, 5 tries)"
 */
export async function fetchBytes(url, options = {}) {
  const o = { ...FETCH_DEFAULTS, ...options };
  const sleep = o.sleep ?? wait;
  for (let attempt = 0; ; attempt++) {
    if (o.signal?.aborted) throw abortError();
    try {
      return await attemptOnce(url, o);
    } catch (e) {
      if (isAbort(e) || !e.retryable || attempt >= o.retries) throw tries(e, attempt + 1);
      const delay = backoffDelay(attempt, o, o.random);
      o.onRetry?.(attempt + 1, delay, e);
      await sleep(delay, o.signal);
    }
  }
}

// The error as it ends: with the number of tries when there were several.
function tries(error, n) {
  if (n === 1 || !(error instanceof FetchError)) return error;
  return new FetchError(error.message.replace(/\)$/, `, ${n} tries)`), error.retryable);
}

// One attempt, aborted by the caller's signal or by a stall of timeoutMs.
async function attemptOnce(url, o) {
  const controller = new AbortController();
  let stalled = false;
  let timer = null;
  const arm = () => {
    clearTimeout(timer);
    timer = setTimeout(() => { stalled = true; controller.abort(); }, o.timeoutMs);
  };
  const forward = () => controller.abort();
  o.signal?.addEventListener('abort', forward);
  arm();
  try {
    let response;
    try {
      response = await o.fetch(url, { signal: controller.signal });
    } catch (e) {
      throw failure(e, url, stalled, o);
    }
    if (response.status === 404) throw new FetchError(`${url} is missing (HTTP 404)`, false);
    if (!response.ok) {
      throw new FetchError(`${url} could not be loaded (HTTP ${response.status})`, retryableStatus(response.status));
    }
    try {
      return await readBody(response, () => arm(), o, controller.signal);
    } catch (e) {
      throw failure(e, url, stalled, o);
    }
  } finally {
    clearTimeout(timer);
    o.signal?.removeEventListener('abort', forward);
  }
}

// An exception of fetch or of reading the body as this module reports it.
function failure(e, url, stalled, o) {
  if (stalled) return new FetchError(`could not fetch ${url} (no data for ${o.timeoutMs / 1000} s)`, true);
  if (o.signal?.aborted) return abortError();
  return new FetchError(`could not fetch ${url} (${e?.message ?? e})`, true);
}

// The body's bytes, calling progress() and o.onBytes(n) as they arrive.
async function readBody(response, progress, o, signal) {
  if (!response.body) {
    const bytes = new Uint8Array(await response.arrayBuffer());
    o.onBytes?.(bytes.length);
    return bytes;
  }
  const reader = response.body.getReader();
  const cancel = () => reader.cancel().catch(() => {});
  signal.addEventListener('abort', cancel);  // a stand-in body may not watch the signal itself
  try {
    const onPiece = (piece) => {
      o.onBytes?.(piece.length);
      progress();
    };
    const bytes = await readAll(reader, { expected: o.expectedBytes, onPiece });
    if (signal.aborted) throw abortError();
    return bytes;
  } finally {
    signal.removeEventListener('abort', cancel);
  }
}

/** Resolves after ms, or rejects with an AbortError when `signal` aborts first. */
export function wait(ms, signal) {
  return new Promise((resolve, reject) => {
    if (signal?.aborted) return reject(abortError());
    const done = () => { signal?.removeEventListener('abort', stop); resolve(); };
    const timer = setTimeout(done, ms);
    const stop = () => { clearTimeout(timer); reject(abortError()); };
    signal?.addEventListener('abort', stop, { once: true });
  });
}

/**
 * A stream folder's files, fetched with one set of settings: every stream kind (stream.js,
 * model_stream.js) holds one, so each file of each kind gets the same timeout and retries.
 */
export class StreamFolder {
  /**
   * @param {string} base folder URL ("stream/")
   * @param {object} [options] fetch (the fetch to use), FETCH_DEFAULTS' fields, random and sleep
   *   (jitter and wait, for tests), onRetry(file, attempt, delayMs, error) before each retry
   */
  constructor(base, options = {}) {
    this.base = base.endsWith('/') ? base : `${base}/`;
    const fetch = options.fetch ?? ((url, init) => globalThis.fetch(url, init));
    this.settings = {
      fetch, random: options.random, sleep: options.sleep,
      ...Object.fromEntries(Object.keys(FETCH_DEFAULTS).map((k) => [k, options[k] ?? FETCH_DEFAULTS[k]])),
    };
    this.onRetry = options.onRetry ?? (() => {});
  }

  /** URL of a file of the folder. */
  url(file) {
    return this.base + file;
  }

  /** GET a file of the folder (fetchBytes' extra options: signal, onBytes, expectedBytes). */
  get(file, extra = {}) {
    return fetchBytes(this.url(file), {
      ...this.settings, ...extra,
      onRetry: (attempt, delay, error) => this.onRetry(file, attempt, delay, error),
    });
  }

  /** GET a file the manifest gives the size of; a file of another size is an error no retry mends. */
  async getSized(file, bytes, extra = {}) {
    const got = await this.get(file, { ...extra, expectedBytes: bytes });
    const where = this.url(file);
    if (got.length < bytes) throw new Error(`${where} is truncated (got ${got.length} of ${bytes} bytes)`);
    if (got.length > bytes) throw new Error(`${where} is ${got.length} bytes, the manifest says ${bytes}`);
    return got;
  }
}
