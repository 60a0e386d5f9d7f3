// window.js FetchWindow's rule for items whose load failed (retry.js), with a fake clock and a
// stand-in load: after an outage's failure an item is fetched again once the playhead wants it
// and a wait that doubles per failure in a row (5, 10, 20, 30, 30 s) has passed, never sooner;
// a missing file only when asked for; a seek asks at once.
import assert from 'node:assert/strict';
import { test } from 'node:test';

import { FetchError } from '../../atgs/web/player/fetcher.js';
import { FetchWindow } from '../../atgs/web/player/window.js';

const flush = () => new Promise((r) => setImmediate(r));

// A clock whose time moves only by advance(ms), firing the timers due on the way in time order.
function fakeClock() {
  let now = 0, ids = 0;
  const timers = new Map();
  return {
    now: () => now,
    setTimeout: (fn, ms) => { timers.set(++ids, { at: now + ms, fn }); return ids; },
    clearTimeout: (id) => { timers.delete(id); },
    pending: () => timers.size,
    async advance(ms) {
      const end = now + ms;
      for (;;) {
        const due = [...timers].filter(([, t]) => t.at <= end).sort((a, b) => a[1].at - b[1].at)[0];
        if (!due) break;
        timers.delete(due[0]);
        now = Math.max(now, due[1].at);
        due[1].fn();
        await flush();
      }
      now = end;
      await flush();
    },
  };
}

// A load that answers item i with outcome(i): a value, or a thrown error; it logs [i, time] per call.
function standInLoad(clock, outcome) {
  const calls = [];
  const load = async (i) => {
    calls.push([i, clock.now()]);
    const result = outcome(i);
    if (result instanceof Error) throw result;
    return result;
  };
  const times = (i) => calls.filter(([j]) => j === i).map(([, t]) => t);
  return { load, calls, times };
}

const outage = () => new FetchError('could not fetch chunk_1.bin (Failed to fetch, 5 tries)', true);
const missing = () => new FetchError('chunk_1.bin is missing (HTTP 404)', false);

function windowOf(n, clock, load, extra = {}) {
  const failures = [];
  const w = new FetchWindow({
    sizes: new Array(n).fill(10), load, clock, budgetBytes: 1000, ...extra,
    onFailed: (i, e, retryAt) => failures.push([i, clock.now(), retryAt]),
  });
  return { w, failures };
}

test('after an outage an item is fetched again after 5, 10, 20, 30, 30 s, never sooner; once it loads the wait starts over', async () => {
  const clock = fakeClock();
  let down = true;
  const { load, times } = standInLoad(clock, (i) => (i === 1 && down ? outage() : `item ${i}`));
  const { w, failures } = windowOf(3, clock, load, { wrap: false });
  w.setPlayhead(0);
  await flush();
  assert.deepEqual(times(1), [0]);
  // the rule, written out: after the k-th failure in a row, min(30, 5 * 2^(k-1)) s
  const expected = [0];
  for (let k = 1; k <= 6; k++) expected.push(expected[k - 1] + 1000 * Math.min(30, 5 * 2 ** (k - 1)));
  for (let t = 0; t < expected[5]; t += 500) {
    await clock.advance(500);
    const f = w.failure(1);
    const next = expected.find((e) => e > clock.now());
    assert.equal(f?.retryAt, next, `t = ${clock.now()}`);  // the failure stands until the next try
    await assert.rejects(w.get(1), /Failed to fetch/);
  }
  assert.deepEqual(times(1), expected.slice(0, 6));
  assert.deepEqual(failures.map(([i, at, retryAt]) => [i, at, retryAt - at]),
    expected.slice(0, 6).map((t, k) => [1, t, 1000 * Math.min(30, 5 * 2 ** k)]));
  assert.equal(w.peek(0), 'item 0');
  assert.equal(w.peek(2), 'item 2');  // the others load meanwhile
  assert.ok(w.full(), 'held or waiting: nothing to fetch now');
  assert.equal(w.heldBytes, 20, 'a failed item holds none of the budget');

  down = false;  // the network is back: the next try (30 s later) loads it
  await clock.advance(29999);
  assert.equal(times(1).length, 6);
  assert.ok(w.failure(1), 'still waiting');
  await clock.advance(1);
  assert.equal(times(1)[6], expected[6]);
  assert.equal(times(1).length, 7);
  assert.equal(w.peek(1), 'item 1');
  assert.equal(w.failure(1), undefined);
  assert.equal(await w.get(1), 'item 1');

  down = true;  // a later outage: the first wait again, not the last
  w.setPlayhead(2);  // item 1 leaves the window (0 and 1 dropped), then comes back
  w.setPlayhead(1);
  await flush();
  const before = times(1).length;
  assert.equal(w.failure(1).retryAt - clock.now(), 5000);
  await clock.advance(4999);
  assert.equal(times(1).length, before);
  await clock.advance(1);
  assert.equal(times(1).length, before + 1);
  w.close();
  assert.equal(clock.pending(), 0, 'a closed window sets no timer');
});

test('a failure that passes is fetched again when the playhead next wants the item, not while it is out of the window', async () => {
  const clock = fakeClock();
  let down = true;
  const { load, times } = standInLoad(clock, (i) => (i === 1 && down ? outage() : i));
  const { w } = windowOf(6, clock, load, { maxItems: 2 });
  w.setPlayhead(0);
  await flush();
  assert.deepEqual(times(1), [0]);
  w.setPlayhead(3);  // items 3 and 4 now: 1 is not wanted
  await clock.advance(120000);
  assert.deepEqual(times(1), [0], 'not fetched for nobody');
  down = false;
  w.setPlayhead(1);  // the playhead reaches it: its wait is long over, fetched at once
  await flush();
  assert.deepEqual(times(1), [0, 120000]);
  assert.equal(w.peek(1), 1);
  w.close();
});

test('a missing file or a wrong size is not fetched again on its own, however long; asked for (a seek), once at once', async () => {
  for (const error of [missing(), new Error('chunk_1.bin is 12 bytes, the manifest says 10')]) {
    const clock = fakeClock();
    const { load, times } = standInLoad(clock, (i) => (i === 1 ? error : i));
    const { w, failures } = windowOf(3, clock, load);
    w.setPlayhead(0);
    await flush();
    assert.deepEqual(failures, [[1, 0, Infinity]]);
    assert.equal(clock.pending(), 0, 'no timer for it');
    for (let k = 0; k < 60; k++) {
      await clock.advance(10000);
      w.setPlayhead(k % 3);  // played onto, past, around: not asked for
      await flush();
    }
    assert.deepEqual(times(1), [0], 'ten minutes: one request');
    w.setPlayhead(1);
    w.forget(1);  // a seek onto it
    await flush();
    assert.deepEqual(times(1), [0, 600000]);
    assert.equal(failures.length, 2);
    assert.equal(w.failure(1).retryAt, Infinity);  // still missing: standing again until asked
    await clock.advance(600000);
    assert.equal(times(1).length, 2);
    w.close();
  }
});

test('a seek onto an item waiting out an outage fetches it at once; its failures in a row still count', async () => {
  const clock = fakeClock();
  const { load, times } = standInLoad(clock, (i) => (i === 1 ? outage() : i));
  const { w, failures } = windowOf(3, clock, load);
  w.setPlayhead(0);
  await flush();
  await clock.advance(2000);
  w.forget(1);  // a seek at 2 s: not 5 s
  await flush();
  assert.deepEqual(times(1), [0, 2000]);
  assert.equal(failures[1][2] - failures[1][1], 10000, 'its second failure in a row waits 10 s');
  w.forget(0);  // asking for an item that did not fail, and is held: fetched again
  await flush();
  assert.deepEqual(times(0), [0, 2000]);
  w.close();
});

test('an item aborted by the playhead is not a failure; one in flight is not fetched twice when asked for', async () => {
  const clock = fakeClock();
  const calls = [];
  const load = (i, signal) => new Promise((resolve, reject) => {
    calls.push(i);
    signal.addEventListener('abort', () => reject(new DOMException('aborted', 'AbortError')));
  });
  const { w, failures } = windowOf(6, clock, load, { maxItems: 2 });
  w.setPlayhead(0);
  w.forget(0);
  w.setPlayhead(4);
  await flush();
  assert.deepEqual(calls, [0, 1, 4, 5]);
  assert.deepEqual(failures, []);
  assert.equal(w.failure(0), undefined);
  w.close();
});
