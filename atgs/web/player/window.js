// The look-ahead window of a stream in bounded memory (docs/web.md, "Streaming"): items 0..n-1
// of known byte sizes (a stream's files, in playing order), of which only those from the playhead
// on, up to a byte budget (and optionally a number of items), are fetched and kept. Moving the
// playhead evicts what falls out of the window (behind it, or beyond the budget) and aborts its
// downloads; a seek outside the window goes back to the network. Any stream kind keeps its files
// through one of these; what an item is (a chunk, a model part) is its `load`, and a kind whose
// items are not one per playhead position (a model part serves many frames) gives the `order` in
// which it wants them from a playhead. An item whose load failed is fetched again by retry.js's
// rule: after a growing wait if the failure may pass (an outage), else only when asked for (a
// seek onto it); the window's clock times the waits. No DOM: Node tests it with a stand-in load
// and clock.

import { isAbort } from './fetcher.js';
import { Failures } from './retry.js';

/** The default budget: 32 MiB of compressed bytes held (a phone's tab holds that easily). */
export const DEFAULT_BUDGET_BYTES = 32 * 2 ** 20;

/** The page's clock: performance.now()'s milliseconds, and its timers. */
export const SYSTEM_CLOCK = Object.freeze({
  now: () => performance.now(),
  setTimeout: (fn, ms) => setTimeout(fn, ms),
  clearTimeout: (id) => clearTimeout(id),
});

/** The items in playing order from item `playhead` on (past the last back to 0 when `wrap`). */
export function* playingOrder(playhead, wrap, n) {
  for (let k = 0; k < n; k++) {
    if (!wrap && playhead + k >= n) return;
    yield (playhead + k) % n;
  }
}

export class FetchWindow {
  /**
   * @param {object} o
   * @param {number[]} o.sizes bytes of each item (what it holds once loaded)
   * @param {(i: number, signal: AbortSignal) => Promise<any>} o.load fetches item i (aborts with signal)
   * @param {number} [o.budgetBytes] bytes held and in flight at most (DEFAULT_BUDGET_BYTES); the
   *   playhead's item is held even when it alone is larger
   * @param {number} [o.maxItems] items held and in flight at most (Infinity)
   * @param {number} [o.maxInFlight] concurrent loads (2)
   * @param {boolean} [o.wrap] the window continues at item 0 past the last (a looping video)
   * @param {(playhead: number, wrap: boolean) => Iterable<number>} [o.order] the items the window
   *   wants from a playhead, most urgent first, each once (playingOrder: the playhead is an item)
   * @param {(i: number) => void} [o.onLoaded]
   * @param {(i: number, error: Error, retryAt: number) => void} [o.onFailed] each time an item's load
   *   fails; retryAt: when the window may fetch it again unasked (a time of `clock`; Infinity:
   *   only once asked for, forget)
   * @param {number} [o.retryDelayMs], [o.maxRetryDelayMs] the waits after a failure (retry.js RETRY_LATER_DEFAULTS)
   * @param {{now: () => number, setTimeout: Function, clearTimeout: Function}} [o.clock] (SYSTEM_CLOCK; tests pass a fake)
   */
  constructor(o) {
    this.sizes = o.sizes;
    this.load = o.load;
    this.budgetBytes = o.budgetBytes ?? DEFAULT_BUDGET_BYTES;
    this.maxItems = o.maxItems ?? Infinity;
    this.maxInFlight = o.maxInFlight ?? 2;
    this.wrap = o.wrap ?? true;
    this.order = o.order ?? ((playhead, wrap) => playingOrder(playhead, wrap, this.sizes.length));
    this.onLoaded = o.onLoaded ?? (() => {});
    this.onFailed = o.onFailed ?? (() => {});
    this.clock = o.clock ?? SYSTEM_CLOCK;
    this.playhead = 0;
    this.items = new Map();     // i -> value, loaded and held
    this.inFlight = new Map();  // i -> AbortController
    this.failures = new Failures(o);  // i -> why it failed, until when it is not fetched
    this.timer = null;          // wakes the window when the first standing failure ends
    this.timerAt = Infinity;
    this.waiters = new Map();   // i -> [{resolve, reject}]
    this.heldBytes = 0;         // of items and loads in flight (a load reserves its item's size)
    this.peakBytes = 0;
    this.peakItems = 0;
    this.loads = 0;             // loads started (a reload after an eviction counts again)
    this.closed = false;
  }

  /** The items of the window, in the order they are fetched: the playhead's first (`order`). */
  wanted() {
    const out = [];
    if (this.closed) return out;
    let bytes = 0;
    for (const i of this.order(this.playhead, this.wrap)) {
      if (out.length >= this.maxItems) break;
      if (out.length > 0 && bytes + this.sizes[i] > this.budgetBytes) break;
      bytes += this.sizes[i];
      out.push(i);
    }
    return out;
  }

  /** Item i if it is held now, else undefined. */
  peek(i) {
    return this.items.get(i);
  }

  /**
   * Item i's failure while it stands ({error, count, retryAt}: not fetched before retryAt, a time
   * of the window's clock, Infinity: until asked for), else undefined.
   */
  failure(i) {
    return this.failures.standing(i, this.clock.now());
  }

  /** True when every item of the window is held (or failed): nothing more to fetch until the playhead moves or a failure ends. */
  full() {
    return this.wanted().every((i) => this.items.has(i) || this.failure(i));
  }

  /**
   * What the window holds, in the player's state() names (docs/web.md): bytes and items held and
   * in flight, their peaks, its budget and item limit, loads started, whether it is complete.
   */
  memory() {
    return {
      heldBytes: this.heldBytes, heldChunks: this.heldItems, peakHeldBytes: this.peakBytes, peakHeldChunks: this.peakItems,
      windowBudgetBytes: this.budgetBytes, maxChunks: this.maxItems, downloads: this.loads, windowFull: this.full(),
    };
  }

  /** [bytes held, bytes wanted] of the window's items: the page's loading bar. */
  progress() {
    const wanted = this.wanted();
    const target = wanted.reduce((sum, i) => sum + this.sizes[i], 0);
    const held = wanted.reduce((sum, i) => sum + (this.items.has(i) ? this.sizes[i] : 0), 0);
    return [held, target];
  }

  /** Items held and in flight. */
  get heldItems() {
    return this.items.size + this.inFlight.size;
  }

  /**
   * Move the window to start at item i: drop the items and abort the loads outside it, then
   * fetch what it lacks in order.
   */
  setPlayhead(i) {
    this.playhead = i;
    this._update();
  }

  setWrap(wrap) {
    this.wrap = wrap;
    this._update();
  }

  /**
   * Item i once loaded (at once when held). An item outside the window is not fetched for this:
   * the promise waits until the playhead brings it in (move the playhead first).
   * @returns {Promise<any>} rejects with the item's error while its failure stands (failure(i))
   */
  get(i) {
    if (this.items.has(i)) return Promise.resolve(this.items.get(i));
    const failure = this.failure(i);
    if (failure) return Promise.reject(failure.error);
    return new Promise((resolve, reject) => {
      if (!this.waiters.has(i)) this.waiters.set(i, []);
      this.waiters.get(i).push({ resolve, reject });
    });
  }

  /**
   * Item i is asked for again (a seek onto it): its failure no longer stands, or the copy held
   * (that proved bad) is dropped, so it is fetched now if it is in the window (else when the
   * playhead brings it in). Its failures in a row still count for the next wait.
   */
  forget(i) {
    if (this.items.has(i)) this._drop(i);
    this.failures.forgive(i, this.clock.now());
    this._update();
  }

  /** Abort every load and drop every item: the window holds nothing after this. */
  close() {
    this.closed = true;
    this._update();
  }

  _update() {
    const wanted = this.wanted();
    const keep = new Set(wanted);
    for (const i of [...this.items.keys()]) {
      if (!keep.has(i)) this._drop(i);
    }
    for (const [i, controller] of [...this.inFlight]) {
      if (!keep.has(i)) {
        this.inFlight.delete(i);
        this.heldBytes -= this.sizes[i];
        controller.abort();
      }
    }
    for (const i of wanted) {
      if (this.inFlight.size >= this.maxInFlight) break;
      if (!this.items.has(i) && !this.inFlight.has(i) && !this.failure(i)) this._start(i);
    }
    this._wakeAtNextRetry();
  }

  // One timer, at the end of the first standing failure that ends on its own: the window looks
  // again then (and fetches the item if the playhead still wants it; if not, when it does).
  _wakeAtNextRetry() {
    const now = this.clock.now();
    const next = this.closed ? Infinity : this.failures.nextEnd(now);
    if (next === this.timerAt) return;
    if (this.timer !== null) this.clock.clearTimeout(this.timer);
    this.timer = null;
    this.timerAt = next;
    if (next === Infinity) return;
    this.timer = this.clock.setTimeout(() => {
      this.timer = null;
      this.timerAt = Infinity;
      this._update();
    }, next - now);
  }

  _drop(i) {
    this.items.delete(i);
    this.heldBytes -= this.sizes[i];
  }

  _start(i) {
    const controller = new AbortController();
    this.inFlight.set(i, controller);
    this.heldBytes += this.sizes[i];
    this.loads++;
    this.peakBytes = Math.max(this.peakBytes, this.heldBytes);
    this.peakItems = Math.max(this.peakItems, this.heldItems);
    this.load(i, controller.signal).then(
      (value) => {
        if (this.inFlight.get(i) !== controller) return;  // aborted: its reservation is already released
        this.inFlight.delete(i);
        this.items.set(i, value);
        this.failures.succeeded(i);
        this.onLoaded(i);
        this._settle(i, (w) => w.resolve(value));
        this._update();
      },
      (error) => {
        if (this.inFlight.get(i) !== controller) return;
        this.inFlight.delete(i);
        this.heldBytes -= this.sizes[i];
        if (isAbort(error)) return;
        const { retryAt } = this.failures.failed(i, error, this.clock.now());
        this.onFailed(i, error, retryAt);
        this._settle(i, (w) => w.reject(error));
        this._update();
      },
    );
  }

  _settle(i, how) {
    const waiting = this.waiters.get(i) ?? [];
    this.waiters.delete(i);
    for (const w of waiting) how(w);
  }
}
