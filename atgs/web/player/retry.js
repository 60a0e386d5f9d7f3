// When a window item whose download failed (fetcher.js's retries spent) is fetched again
// (docs/web.md, "Streaming"): a failure that may pass on its own (a network error, a stall, HTTP
// 408, 429 or 5xx: an outage, an overloaded server) is forgotten after a wait that doubles with
// each failure of that item in a row, capped; one no retry mends (HTTP 404 or another 4xx, a size
// the manifest does not give, a corrupt file) only when the viewer asks for the item again (a
// seek onto it, Play). No timers and no DOM: FetchWindow (window.js) owns the clock.

/** The wait after the item's 1st failure in a row, doubled after each next one, capped: 5, 10, 20, 30, 30 s... */
export const RETRY_LATER_DEFAULTS = Object.freeze({ retryDelayMs: 5000, maxRetryDelayMs: 30000 });

/** True for a failure another try may not get (fetcher.js FetchError.retryable): fetched again unasked. */
export function passesOnItsOwn(error) {
  return error?.retryable === true;
}

/** The wait after an item's `failures`-th failure in a row (1: the first). */
export function retryDelay(failures, { retryDelayMs, maxRetryDelayMs }) {
  return Math.min(maxRetryDelayMs, retryDelayMs * 2 ** (failures - 1));
}

/**
 * The failures of a window's items. A failure stands (the item is not fetched, requests for it
 * reject with its error) until its `retryAt` (a time of the window's clock; Infinity: until
 * asked for); the count of failures in a row outlives it, and a load that succeeds clears it.
 */
export class Failures {
  /** @param {object} [o] RETRY_LATER_DEFAULTS' fields */
  constructor(o = {}) {
    this.delays = { ...RETRY_LATER_DEFAULTS };
    for (const key of Object.keys(RETRY_LATER_DEFAULTS)) if (o[key] !== undefined) this.delays[key] = o[key];
    this.byItem = new Map();  // i -> {error, count, retryAt}
  }

  /** Item i's load failed at time `now`: returns its failure {error, count, retryAt}. */
  failed(i, error, now) {
    const count = (this.byItem.get(i)?.count ?? 0) + 1;
    const retryAt = passesOnItsOwn(error) ? now + retryDelay(count, this.delays) : Infinity;
    const failure = { error, count, retryAt };
    this.byItem.set(i, failure);
    return failure;
  }

  /** Item i's failure if it still stands at `now`, else undefined. */
  standing(i, now) {
    const failure = this.byItem.get(i);
    return failure && now < failure.retryAt ? failure : undefined;
  }

  /** Item i was asked for (a seek onto it): it may be fetched at once; its count stays. */
  forgive(i, now) {
    const failure = this.byItem.get(i);
    if (failure) failure.retryAt = Math.min(failure.retryAt, now);
  }

  /** Item i loaded: its next failure waits the first delay again. */
  succeeded(i) {
    this.byItem.delete(i);
  }

  /** The earliest time after `now` at which a standing failure ends on its own (Infinity: none does). */
  nextEnd(now) {
    let next = Infinity;
    for (const f of this.byItem.values()) if (f.retryAt > now && f.retryAt < next) next = f.retryAt;
    return next;
  }
}
