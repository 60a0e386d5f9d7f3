// fetcher.js with stand-in fetches: retries and their back-off, stalls, aborts, what is not retried.
import assert from 'node:assert/strict';
import { test } from 'node:test';

import { backoffDelay, FETCH_DEFAULTS, fetchBytes } from '../../atgs/web/player/fetcher.js';

const body = new Uint8Array([1, 2, 3, 4, 5]);
const ok = () => new Response(body, { status: 200 });

// A fetch answering with replies[k] on call k (a function of the init: a Response, a promise, or a throw).
function scripted(replies) {
  const calls = [];
  const fetch = (url, init) => {
    calls.push(url);
    const reply = replies[Math.min(calls.length - 1, replies.length - 1)];
    return Promise.resolve().then(() => reply(init));
  };
  return { fetch, calls };
}

// A fetch that never answers until its signal aborts (a dead connection).
const never = (init) => new Promise((_, reject) => {
  init.signal.addEventListener('abort', () => reject(new DOMException('aborted', 'AbortError')));
});

// A response whose body sends `first` bytes, then nothing more (a connection that stalls mid-body).
const stallsMidBody = (first) => () => new Response(new ReadableStream({
  start(c) { c.enqueue(body.subarray(0, first)); },
}), { status: 200 });

test('the back-off doubles from backoffMs, is capped at maxBackoffMs, with a jitter factor in [0.5, 1)', () => {
  const o = { backoffMs: 100, maxBackoffMs: 1000 };
  for (const [attempt, base] of [[0, 100], [1, 200], [2, 400], [3, 800], [4, 1000], [9, 1000]]) {
    assert.equal(backoffDelay(attempt, o, () => 0), 0.5 * base);
    assert.ok(Math.abs(backoffDelay(attempt, o, () => 0.999999) - base) < 1e-3);
  }
  assert.deepEqual(Object.keys(FETCH_DEFAULTS).sort(), ['backoffMs', 'maxBackoffMs', 'retries', 'timeoutMs']);
});

test('server errors and network errors are retried with the back-off, then succeed', async () => {
  const { fetch, calls } = scripted([
    () => new Response('', { status: 503 }),
    () => { throw new TypeError('Failed to fetch'); },
    () => new Response('', { status: 429 }),
    ok,
  ]);
  const waits = [];
  const retries = [];
  const got = await fetchBytes('s/a.bin', {
    fetch, random: () => 0.5, sleep: async (ms) => { waits.push(ms); },
    onRetry: (attempt, delay, e) => retries.push([attempt, delay, e.message]),
  });
  assert.deepEqual([...got], [...body]);
  assert.equal(calls.length, 4);
  const b = FETCH_DEFAULTS.backoffMs;
  assert.deepEqual(waits, [0.75 * b, 1.5 * b, 3 * b]);
  assert.deepEqual(retries.map((r) => r[2]), [
    's/a.bin could not be loaded (HTTP 503)', 'could not fetch s/a.bin (Failed to fetch)', 's/a.bin could not be loaded (HTTP 429)']);
});

test('after the last retry the error names the file and the tries; a 404 or a 403 is not retried', async () => {
  const failing = scripted([() => new Response('', { status: 500 })]);
  await assert.rejects(fetchBytes('s/b.bin', { fetch: failing.fetch, retries: 2, sleep: async () => {} }),
    { message: 's/b.bin could not be loaded (HTTP 500, 3 tries)' });
  assert.equal(failing.calls.length, 3);
  for (const [status, message] of [[404, 's/c.bin is missing (HTTP 404)'], [403, 's/c.bin could not be loaded (HTTP 403)']]) {
    const once = scripted([() => new Response('', { status })]);
    await assert.rejects(fetchBytes('s/c.bin', { fetch: once.fetch, sleep: async () => {} }), { message });
    assert.equal(once.calls.length, 1);
  }
});

test('a request without headers or without body bytes for timeoutMs is aborted and retried', async () => {
  const noHeaders = scripted([never, ok]);
  const got = await fetchBytes('s/d.bin', { fetch: noHeaders.fetch, timeoutMs: 20, sleep: async () => {} });
  assert.deepEqual([...got], [...body]);
  assert.equal(noHeaders.calls.length, 2);
  const midBody = scripted([stallsMidBody(2), stallsMidBody(3), ok]);
  const arrived = [];
  assert.deepEqual([...await fetchBytes('s/e.bin', { fetch: midBody.fetch, timeoutMs: 20, sleep: async () => {}, onBytes: (n) => arrived.push(n) })], [...body]);
  assert.deepEqual(arrived, [2, 3, 5], 'every attempt\'s bytes are counted: they crossed the network');
  const dead = scripted([never]);
  await assert.rejects(fetchBytes('s/f.bin', { fetch: dead.fetch, timeoutMs: 10, retries: 1, sleep: async () => {} }),
    { message: 'could not fetch s/f.bin (no data for 0.01 s, 2 tries)' });
});

test('a body that keeps arriving is not cut by the stall timeout, however long it takes', async () => {
  const slow = () => new Response(new ReadableStream({
    async start(c) {
      for (const b of body) {
        await new Promise((r) => setTimeout(r, 8));
        c.enqueue(new Uint8Array([b]));
      }
      c.close();
    },
  }), { status: 200 });
  const { fetch, calls } = scripted([slow]);
  assert.deepEqual([...await fetchBytes('s/g.bin', { fetch, timeoutMs: 25 })], [...body]);  // 40 ms in all
  assert.equal(calls.length, 1);
});

test('the caller\'s abort ends the request and the back-off wait, with no retry', async () => {
  const hanging = scripted([never]);
  const controller = new AbortController();
  const pending = fetchBytes('s/h.bin', { fetch: hanging.fetch, signal: controller.signal });
  setTimeout(() => controller.abort(), 5);
  await assert.rejects(pending, { name: 'AbortError' });
  assert.equal(hanging.calls.length, 1);

  const failing = scripted([() => new Response('', { status: 502 })]);
  const c2 = new AbortController();
  const started = Date.now();
  const waiting = fetchBytes('s/i.bin', { fetch: failing.fetch, signal: c2.signal, backoffMs: 60000, maxBackoffMs: 60000 });
  setTimeout(() => c2.abort(), 10);
  await assert.rejects(waiting, { name: 'AbortError' });
  assert.ok(Date.now() - started < 5000, 'the minute of back-off was cut short');
  assert.equal(failing.calls.length, 1);
});

test('readAll: the expected size in one buffer; a shorter or a longer stream still comes out whole', async () => {
  const { readAll } = await import('../../atgs/web/player/read.js');
  const pieces = (...lengths) => {
    let k = 0;
    return new ReadableStream({
      start(c) {
        for (const n of lengths) c.enqueue(Uint8Array.from({ length: n }, () => k++ % 251));
        c.close();
      },
    }).getReader();
  };
  const want = (n) => Array.from({ length: n }, (_, i) => i % 251);
  const seen = [];
  const exact = await readAll(pieces(3, 4, 5), { expected: 12, onPiece: (p) => seen.push(p.length) });
  assert.deepEqual([...exact], want(12));
  assert.equal(exact.buffer.byteLength, 12, 'one buffer of the expected size');
  assert.deepEqual(seen, [3, 4, 5]);
  assert.deepEqual([...await readAll(pieces(3, 4), { expected: 12 })], want(7));
  assert.deepEqual([...await readAll(pieces(3, 4, 5, 6), { expected: 12 })], want(18));
  assert.deepEqual([...await readAll(pieces(300, 2))], want(302));
});

test('readAll: an expected size no buffer can take still reads what comes', async () => {
  const { readAll } = await import('../../atgs/web/player/read.js');
  const reader = new ReadableStream({ start(c) { c.enqueue(new Uint8Array([7, 8])); c.close(); } }).getReader();
  assert.deepEqual([...await readAll(reader, { expected: 2 ** 53 })], [7, 8]);
});
