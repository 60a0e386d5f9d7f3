// stream.js with a stand-in fetch serving a stream folder from memory.
import assert from 'node:assert/strict';
import { test } from 'node:test';

import { decodedBytes, Stream } from '../../atgs/web/player/stream.js';
import { encodeStream, random, randomRecord } from './encode.mjs';

// n chunks of F frames of G Gaussians (S static).
function folder(n, { F = 3, G = 12, S = 4, seed = 1 } = {}) {
  const rand = random(seed);
  const chunks = [];
  for (let c = 0; c < n; c++) {
    const statics = Array.from({ length: S }, () => randomRecord(rand));
    const frames = Array.from({ length: F }, () => [...statics, ...Array.from({ length: G - S }, () => randomRecord(rand))]);
    chunks.push({ S, frames });
  }
  return encodeStream(chunks, { chunkFrames: F });
}

// A fetch over `files` whose responses wait until release(name) (or at once with auto = true);
// it records the order of requests, the most requests open at once, and the requests aborted
// (through the fetch's signal) before their response.
function standIn(files, { auto = true, override = {} } = {}) {
  const log = { requested: [], aborted: [], open: 0, maxOpen: 0, live: new Set() };
  const pending = new Map();
  const fetch = (url, init = {}) => {
    const name = url.replace(/^stream\//, '');
    log.requested.push(name);
    log.live.add(name);
    log.open++;
    log.maxOpen = Math.max(log.maxOpen, log.open);
    return new Promise((resolve, reject) => {
      let done = false;
      const respond = () => {
        if (done) return;
        done = true;
        log.open--;
        log.live.delete(name);
        if (override[name]) return resolve(override[name]());
        const body = files.get(name);
        resolve(body ? new Response(body, { status: 200 }) : new Response('not found', { status: 404 }));
      };
      init.signal?.addEventListener('abort', () => {
        if (done) return;
        done = true;
        log.open--;
        log.live.delete(name);
        log.aborted.push(name);
        pending.delete(name);
        reject(new DOMException('aborted', 'AbortError'));
      });
      if (auto || name === 'manifest.json') respond(); else pending.set(name, respond);
    });
  };
  const release = (name) => {
    const respond = pending.get(name);
    pending.delete(name);
    respond();
  };
  return { fetch, log, release, pending };
}

// No real waits between retries in these tests.
const noWait = { sleep: () => Promise.resolve() };

const tick = () => new Promise((r) => setTimeout(r, 5));

test('loads the manifest, then every chunk in order, two at a time, counting the bytes', async () => {
  const { files, manifest } = folder(5);
  const { fetch, log } = standIn(files);
  const progress = [];
  const loaded = [];
  const stream = new Stream('stream/', { fetch, onProgress: (a, b) => progress.push([a, b]), onChunkLoaded: (i) => loaded.push(i) });
  await stream.open();
  const chunks = await Promise.all([0, 1, 2, 3, 4].map((i) => stream.chunk(i)));
  assert.deepEqual(log.requested, ['manifest.json', ...manifest.chunks.map((c) => c.file)]);
  assert.ok(log.maxOpen <= 2);
  const total = manifest.chunks.reduce((n, c) => n + c.bytes, 0);
  assert.equal(stream.totalBytes, total);
  assert.equal(stream.fetchedBytes, total);
  assert.deepEqual(progress[progress.length - 1], [total, total]);
  assert.deepEqual(loaded, [0, 1, 2, 3, 4]);
  assert.equal(chunks[2].F, 3);
  assert.equal(chunks[2].G, 12);
  assert.deepEqual(stream.locate(7), { chunk: 2, local: 1 });
});

test('at most two requests in flight; the playhead chunk goes next', async () => {
  const { files } = folder(8);
  const { fetch, log, release } = standIn(files, { auto: false });
  const stream = new Stream('stream/', { fetch });
  await stream.open();
  assert.deepEqual(log.requested.slice(1), ['chunk_000000.bin', 'chunk_000001.bin']);
  stream.setPlayhead(6);  // a seek: chunk 6 is needed now
  assert.equal(log.requested.length, 3, 'no third request while two are open');
  release('chunk_000000.bin');
  await tick();
  release('chunk_000001.bin');
  await tick();
  assert.deepEqual(log.requested.slice(3), ['chunk_000006.bin', 'chunk_000007.bin']);
  release('chunk_000006.bin');
  await tick();
  // past the end it wraps to the first chunk not loaded
  assert.equal(log.requested[5], 'chunk_000002.bin');
  assert.equal(log.maxOpen, 2);
  assert.ok(stream.isLoaded(6) && !stream.isLoaded(7));
  stream.close();
  assert.deepEqual(log.aborted.sort(), ['chunk_000002.bin', 'chunk_000007.bin']);
});

test('decoded chunks: at most maxDecoded kept; compressed bytes kept for all the budget holds', async () => {
  const { files } = folder(5);
  const stream = new Stream('stream/', { fetch: standIn(files).fetch, maxDecoded: 2 });
  await stream.open();
  for (const i of [0, 1, 2, 3]) await stream.chunk(i);
  assert.deepEqual([...stream.decoded.keys()], [2, 3]);
  assert.equal(stream.decodedNow(0), null);
  assert.ok(stream.decodedNow(3));
  assert.ok([0, 1, 2, 3].every((i) => stream.isLoaded(i)));
  assert.equal((await stream.chunk(0)).F, 3);  // inflated again from the kept bytes
});

async function failure(mutate, options = {}) {
  const { files, manifest } = folder(4);
  mutate(files, manifest);
  const errors = [];
  const stream = new Stream('stream/', { fetch: standIn(files, options).fetch, onError: (e) => errors.push(e.message), ...noWait });
  let thrown = null;
  try {
    await stream.open();
    await Promise.all([0, 1, 2, 3].map((i) => stream.chunk(i)));
  } catch (e) {
    thrown = e.message;
  }
  stream.close();  // no retry of a failure that may pass outlives the test
  assert.equal(errors.length, 1, 'reported once');
  assert.equal(thrown, errors[0]);
  return errors[0];
}

test('a truncated chunk, a missing one, a corrupt one, one that does not match the manifest', async () => {
  let size = 0;
  assert.equal(await failure((files) => {
    size = files.get('chunk_000003.bin').length;
    files.set('chunk_000003.bin', files.get('chunk_000003.bin').subarray(0, 100));
  }), `stream/chunk_000003.bin is truncated (got 100 of ${size} bytes)`);
  assert.equal(await failure((files) => files.delete('chunk_000001.bin')), 'stream/chunk_000001.bin is missing (HTTP 404)');
  assert.match(await failure((files) => {
    const b = files.get('chunk_000002.bin').slice();
    b.fill(7, 20, 60);
    files.set('chunk_000002.bin', b);
  }), /^stream\/chunk_000002\.bin is corrupt: /);
  assert.match(await failure((files, manifest) => {
    manifest.chunks[1].gaussians = 13;
    files.set('manifest.json', new TextEncoder().encode(JSON.stringify(manifest)));
  }), /^stream\/chunk_000001\.bin does not match the manifest: G = 12, the manifest says 13$/);
  assert.match(await failure((files) => files.set('chunk_000000.bin', new Uint8Array([...files.get('chunk_000000.bin'), 0]))),
    /^stream\/chunk_000000\.bin is \d+ bytes, the manifest says \d+$/);
  assert.equal(await failure(() => {}, { override: { 'chunk_000002.bin': () => new Response('', { status: 500 }) } }),
    'stream/chunk_000002.bin could not be loaded (HTTP 500, 5 tries)');
});

test('a missing chunk stays failed until a seek asks for it; the others load and decode', async () => {
  const { files } = folder(4);
  const original = files.get('chunk_000001.bin');
  files.delete('chunk_000001.bin');
  const errors = [];
  const { fetch, log } = standIn(files);
  const stream = new Stream('stream/', { fetch, onError: (e, i, retryAt) => errors.push([i, e.message, retryAt]) });
  await stream.open();
  await assert.rejects(stream.chunk(1), { message: 'stream/chunk_000001.bin is missing (HTTP 404)' });
  for (const i of [0, 2, 3]) assert.equal((await stream.chunk(i)).G, 12);
  await assert.rejects(stream.chunk(1), { message: 'stream/chunk_000001.bin is missing (HTTP 404)' });
  assert.deepEqual(errors, [[1, 'stream/chunk_000001.bin is missing (HTTP 404)', Infinity]]);
  const requests = () => log.requested.filter((f) => f === 'chunk_000001.bin').length;
  assert.equal(requests(), 1, 'not requested again');
  stream.setPlayhead(1);  // played onto: still failed, not fetched
  await tick();
  assert.equal(requests(), 1);
  assert.equal(stream.failure(1).retryAt, Infinity);
  files.set('chunk_000001.bin', original);  // the file is back
  stream.setPlayhead(1, true);  // a seek onto it asks for it: fetched once more, at once
  assert.equal(requests(), 2);
  assert.equal((await stream.chunk(1)).G, 12);
  assert.equal(stream.failure(1), undefined);
});

test('a corrupt chunk is fetched again and decoded again when a seek asks for it', async () => {
  const { files } = folder(3);
  const good = files.get('chunk_000002.bin');
  const bad = good.slice();
  bad.fill(7, 20, 60);
  files.set('chunk_000002.bin', bad);
  const { fetch, log } = standIn(files);
  const stream = new Stream('stream/', { fetch });
  await stream.open();
  await assert.rejects(stream.chunk(2), /chunk_000002\.bin is corrupt/);
  assert.equal(stream.failure(2).retryAt, Infinity);
  files.set('chunk_000002.bin', good);
  stream.setPlayhead(2, true);
  assert.equal((await stream.chunk(2)).G, 12);
  assert.equal(log.requested.filter((f) => f === 'chunk_000002.bin').length, 2);
});

test('manifest errors: missing, not JSON, wrong format, chunks that do not cover the frames', async () => {
  assert.equal(await failure((files) => files.delete('manifest.json')), 'stream/manifest.json is missing (HTTP 404)');
  assert.match(await failure((files) => files.set('manifest.json', new TextEncoder().encode('{"format": '))),
    /^stream\/manifest\.json is not valid JSON/);
  const edit = (change) => (files, manifest) => {
    change(manifest);
    files.set('manifest.json', new TextEncoder().encode(JSON.stringify(manifest)));
  };
  assert.equal(await failure(edit((m) => { m.format = 'other'; })), 'stream/manifest.json: format is "other", not "atgs-web"');
  assert.equal(await failure(edit((m) => { m.version = 2; })), 'stream/manifest.json: version 2 is not supported (this player reads version 1)');
  assert.equal(await failure(edit((m) => { m.chunks.pop(); })),
    'stream/manifest.json: 12 frames in chunks of 3 need 4 chunks, the manifest lists 3');
  assert.equal(await failure(edit((m) => { delete m.render.near; })), 'stream/manifest.json: render.near is missing');
  const rejected = new Stream('stream/', { fetch: () => Promise.reject(new TypeError('Failed to fetch')), retries: 2, ...noWait });
  await assert.rejects(rejected.open(), { message: 'could not fetch stream/manifest.json (Failed to fetch, 3 tries)' });
});

// --- the window: a byte budget ahead of the playhead ---------------------------------------------

// The chunks a window from `playhead` holds under `budget` bytes: the playhead's, then the next
// ones (wrapping) while their sizes add up to at most the budget (docs/web.md, "Streaming").
function expectedWindow(sizes, playhead, budget, wrap = true) {
  const out = [playhead];
  let bytes = sizes[playhead];
  for (let k = 1; k < sizes.length; k++) {
    if (!wrap && playhead + k >= sizes.length) break;
    const i = (playhead + k) % sizes.length;
    if (bytes + sizes[i] > budget) break;
    bytes += sizes[i];
    out.push(i);
  }
  return out.sort((a, b) => a - b);
}

async function settled(stream) {
  for (let k = 0; k < 200 && !stream.memory().windowFull; k++) await tick();
  assert.ok(stream.memory().windowFull, 'the window filled');
}

const held = (stream, n) => Array.from({ length: n }, (_, i) => i).filter((i) => stream.isLoaded(i));

test('playing through twice: the window ahead of the playhead, nothing behind it, the budget never exceeded', async () => {
  const n = 12;
  const { files, manifest } = folder(n, { G: 40, S: 0, seed: 3 });
  const sizes = manifest.chunks.map((c) => c.bytes);
  // the decoded chunks' reserve (two kept and one being inflated, the largest: 17 bytes a
  // Gaussian a frame, their state and fields), then three and a half chunks' worth for the window
  const reserve = 3 * (48 + 17 * 40 * 3 + 17 * 40 + 16 * 40);
  assert.equal(decodedBytes(manifest.chunks[0]), reserve / 3);
  const windowBudget = Math.round(3.5 * sizes.reduce((a, b) => a + b) / n);
  const budget = reserve + windowBudget;
  const { fetch: base, log } = standIn(files);
  let stream = null;
  let worst = 0;
  // at every request: the chunks held plus those being downloaded (the stand-in's open requests)
  const fetch = (url, init) => {
    if (stream?.manifest) {
      const name = url.replace(/^stream\//, '');
      const downloading = new Set([...log.live, name].map((f) => manifest.chunks.findIndex((c) => c.file === f)));
      const bytes = [...new Set([...held(stream, n), ...downloading])].reduce((s, i) => s + sizes[i], 0);
      worst = Math.max(worst, bytes);
    }
    return base(url, init);
  };
  stream = new Stream('stream/', { fetch, budgetBytes: budget });
  await stream.open();
  for (let pass = 0; pass < 2; pass++) {
    for (let i = 0; i < n; i++) {
      stream.setPlayhead(i);
      assert.equal((await stream.chunk(i)).F, 3);
      await settled(stream);
      assert.deepEqual(held(stream, n), expectedWindow(sizes, i, windowBudget), `playhead ${i}`);
      const m = stream.memory();
      assert.equal(m.heldBytes, expectedWindow(sizes, i, windowBudget).reduce((s, j) => s + sizes[j], 0));
      assert.ok(m.heldBytes <= windowBudget);
      assert.equal(m.windowBudgetBytes, windowBudget);
    }
  }
  const m = stream.memory();
  assert.ok(m.peakHeldBytes <= windowBudget, `peak ${m.peakHeldBytes} of ${windowBudget}`);
  assert.ok(worst <= windowBudget && worst >= 2 * Math.min(...sizes), `${worst} bytes held at worst`);
  assert.ok(m.peakHeldChunks < n);
  // every chunk once a pass, and the w chunks the window wraps to at the last chunk once more
  // (the end of the second pass fetches them again: they were dropped when the playhead left them)
  const w = expectedWindow(sizes, n - 1, windowBudget).filter((i) => i < n - 1).length;
  assert.ok(w >= 1);
  assert.equal(log.requested.filter((f) => f !== 'manifest.json').length, 2 * n + w);
  assert.equal(m.fetchedBytes, log.requested.filter((f) => f !== 'manifest.json')
    .reduce((s, f) => s + files.get(f).length, 0));
});

test('a seek outside the window aborts its downloads and fetches there; a seek back fetches the dropped chunks again', async () => {
  const { files } = folder(12);
  const { fetch, log, release } = standIn(files, { auto: false });
  const stream = new Stream('stream/', { fetch, maxChunks: 2 });
  await stream.open();
  assert.deepEqual(log.requested.slice(1), ['chunk_000000.bin', 'chunk_000001.bin']);
  stream.setPlayhead(8);
  assert.deepEqual(log.aborted, ['chunk_000000.bin', 'chunk_000001.bin']);
  assert.deepEqual(log.requested.slice(3), ['chunk_000008.bin', 'chunk_000009.bin']);
  release('chunk_000008.bin');
  release('chunk_000009.bin');
  assert.equal((await stream.chunk(8)).F, 3);
  await tick();
  assert.deepEqual(held(stream, 12), [8, 9]);
  stream.setPlayhead(9);  // inside the window: 8 is dropped, 10 fetched, 9 kept
  assert.deepEqual(held(stream, 12), [9]);
  assert.deepEqual(log.requested.slice(5), ['chunk_000010.bin']);
  release('chunk_000010.bin');
  await tick();
  stream.setPlayhead(0);
  assert.deepEqual(held(stream, 12), []);
  assert.deepEqual(log.requested.slice(6), ['chunk_000000.bin', 'chunk_000001.bin']);
  release('chunk_000000.bin');
  assert.equal((await stream.chunk(0)).F, 3);
  assert.equal(log.requested.filter((f) => f === 'chunk_000000.bin').length, 2);
  assert.ok(stream.memory().peakHeldChunks <= 2);
  stream.close();
});

test('the window wraps past the last chunk only when the video loops; a budget below two chunks holds two', async () => {
  const { files, manifest } = folder(6);
  const sizes = manifest.chunks.map((c) => c.bytes);
  const stream = new Stream('stream/', { fetch: standIn(files).fetch, maxChunks: 3 });
  await stream.open();
  stream.setPlayhead(5);
  await settled(stream);
  assert.deepEqual(held(stream, 6), [0, 1, 5]);
  stream.setWrap(false);
  await settled(stream);
  assert.deepEqual(held(stream, 6), [5]);
  const tiny = new Stream('stream/', { fetch: standIn(files).fetch, budgetBytes: 1 });
  await tiny.open();
  const [first, second] = [...sizes].sort((a, b) => b - a);
  const minimum = 3 * decodedBytes(manifest.chunks[0]) + first + second;
  assert.equal(tiny.memory().budgetBytes, minimum);
  tiny.setPlayhead(2);
  assert.equal((await tiny.chunk(2)).F, 3);
  await settled(tiny);
  assert.deepEqual(held(tiny, 6), [2, 3]);  // the playing chunk and the next: no stall at every chunk
  assert.ok(tiny.memory().peakHeldBytes <= first + second);
});

test('a chunk that fails twice with 503 loads on the third try; one that never answers fails once, the others load', async () => {
  const { files } = folder(4);
  let calls = 0;
  const flaky = () => (++calls <= 2 ? new Response('', { status: 503 }) : new Response(files.get('chunk_000002.bin')));
  const { fetch, log } = standIn(files, { override: { 'chunk_000002.bin': flaky } });
  const retries = [];
  const stream = new Stream('stream/', { fetch, onRetry: (file, attempt) => retries.push([file, attempt]), ...noWait });
  await stream.open();
  assert.equal((await stream.chunk(2)).G, 12);
  assert.deepEqual(retries, [['chunk_000002.bin', 1], ['chunk_000002.bin', 2]]);
  assert.equal(log.requested.filter((f) => f === 'chunk_000002.bin').length, 3);

  const errors = [];
  const silent = (url, init) => (url.endsWith('chunk_000001.bin')
    ? new Promise((_, reject) => init.signal.addEventListener('abort', () => reject(new DOMException('x', 'AbortError'))))
    : standIn(files).fetch(url, init));
  const dead = new Stream('stream/', { fetch: silent, timeoutMs: 10, retries: 1, onError: (e, i) => errors.push([i, e.message]), ...noWait });
  await dead.open();
  await assert.rejects(dead.chunk(1), { message: 'could not fetch stream/chunk_000001.bin (no data for 0.01 s, 2 tries)' });
  for (const i of [0, 2, 3]) assert.equal((await dead.chunk(i)).G, 12);
  assert.deepEqual(errors, [[1, 'could not fetch stream/chunk_000001.bin (no data for 0.01 s, 2 tries)']]);
  dead.close();
});
