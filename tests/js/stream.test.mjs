// stream.js with a stand-in fetch serving a stream folder from memory.
import assert from 'node:assert/strict';
import { test } from 'node:test';

import { Stream } from '../../atgs/web/player/stream.js';
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
// it records the order of requests and the most requests open at once.
function standIn(files, { auto = true, override = {} } = {}) {
  const log = { requested: [], open: 0, maxOpen: 0 };
  const pending = new Map();
  const fetch = (url) => {
    const name = url.replace(/^stream\//, '');
    log.requested.push(name);
    log.open++;
    log.maxOpen = Math.max(log.maxOpen, log.open);
    return new Promise((resolve) => {
      const respond = () => {
        log.open--;
        if (override[name]) return resolve(override[name]());
        const body = files.get(name);
        resolve(body ? new Response(body, { status: 200 }) : new Response('not found', { status: 404 }));
      };
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
  assert.equal(stream.loadedBytes, total);
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
});

test('decoded chunks: at most maxDecoded kept, compressed bytes kept for all', async () => {
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
  const stream = new Stream('stream/', { fetch: standIn(files, options).fetch, onError: (e) => errors.push(e.message) });
  let thrown = null;
  try {
    await stream.open();
    await Promise.all([0, 1, 2, 3].map((i) => stream.chunk(i)));
  } catch (e) {
    thrown = e.message;
  }
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
    'stream/chunk_000002.bin could not be loaded (HTTP 500)');
});

test('a failed chunk stays failed; the others load and decode', async () => {
  const { files } = folder(4);
  files.delete('chunk_000001.bin');
  const errors = [];
  const { fetch, log } = standIn(files);
  const stream = new Stream('stream/', { fetch, onError: (e, i) => errors.push([i, e.message]) });
  await stream.open();
  await assert.rejects(stream.chunk(1), { message: 'stream/chunk_000001.bin is missing (HTTP 404)' });
  for (const i of [0, 2, 3]) assert.equal((await stream.chunk(i)).G, 12);
  await assert.rejects(stream.chunk(1), { message: 'stream/chunk_000001.bin is missing (HTTP 404)' });
  assert.deepEqual(errors, [[1, 'stream/chunk_000001.bin is missing (HTTP 404)']]);
  assert.equal(log.requested.filter((f) => f === 'chunk_000001.bin').length, 1, 'not requested again');
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
  const rejected = new Stream('stream/', { fetch: () => Promise.reject(new TypeError('Failed to fetch')) });
  await assert.rejects(rejected.open(), { message: 'could not fetch stream/manifest.json (Failed to fetch)' });
});
