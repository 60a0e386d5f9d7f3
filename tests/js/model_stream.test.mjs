// model_stream.js without a GPU: the frame it hands the renderer (DecodedFrame) and the parts a
// ModelStream holds from the playhead on within its byte budget, with a stand-in fetch.
import assert from 'node:assert/strict';
import { test } from 'node:test';

import { gzipSync } from 'node:zlib';

import { DECODED_BYTES_PER_SLOT, DecodedFrame, ModelStream } from '../../atgs/web/player/model_stream.js';

// A part file holding no tensors (docs/web.md, "A model part file").
function emptyPart() {
  const header = new TextEncoder().encode('{"tensors":[]}  ');
  const raw = new Uint8Array(12 + header.length);
  raw.set([65, 84, 71, 77], 0);  // ATGM
  new DataView(raw.buffer).setUint16(4, 1, true);
  new DataView(raw.buffer).setUint32(8, header.length, true);
  raw.set(header, 12);
  return new Uint8Array(gzipSync(raw));
}
const PART = emptyPart();

test('a decoded frame hands the renderer its read-backs as they are (layout float, no copy)', () => {
  const count = 3;
  const decoded = {
    count,
    mean: Float32Array.from([0, 1, 2, 0.9, 10, -5, 4, 0.5, 99, 99, 99, 0]),  // the third is dropped
    quat: Float32Array.from([-1, 0, 0, 0, 0.5, 0.5, 0.5, 0.5, 1, 0, 0, 0]),
    scale: Float32Array.from([0.01, 0.02, 0.04, 1, 0.1, 0.2, 0.3, 1, 5, 5, 5, 0]),
    color: Float32Array.from([0, 0.5, 1, 0, 0.25, 0.75, 0.1, 0, 1, 1, 1, 0]),
  };
  const frame = new DecodedFrame(decoded);
  assert.deepEqual([frame.layout, frame.F, frame.G, frame.S, frame.D], ['float', 1, 3, 0, 3]);
  const f = frame.frame(0);
  for (const name of ['mean', 'quat', 'scale', 'color']) assert.equal(f[name], decoded[name], name);  // the same arrays
  // the depth sort reads the positions and the opacities (at 4 i + 3) of the mean texels
  assert.equal(f.position, decoded.mean);
  assert.equal(f.opacity, decoded.mean);
  assert.throws(() => frame.frame(1), RangeError);
});

// A manifest of `n` frames, a keyframe part every 4 frames (a window of two), one hash part a
// 16-frame segment; every part holds `values` floats (4 bytes each once read), 5 anchors of q 2.
const VALUES = 1000;
function manifest(n) {
  const part = (file, kind, extra = {}) => ({ file, kind, bytes: PART.length, values: VALUES, anchors: 0, ...extra });
  const parts = [part('weights.bin', 'weights'), part('anchors_static.bin', 'anchors', { keyframe: -1, anchors: 5 })];
  const kf = Math.ceil(n / 4) + 1;
  for (let k = 0; k < kf; k++) parts.push(part(`anchors_kf_${k}.bin`, 'anchors', { keyframe: k, anchors: 5 }));
  const firstHash = parts.length;
  for (let m = 0; m < Math.ceil(n / 16); m++) parts.push(part(`hash_seg_${m}.bin`, 'hash', { segment: m }));
  const frames = Array.from({ length: n }, (_, f) => ({
    frame: f, segment: Math.floor(f / 16), anchors: [1, 2 + Math.floor(f / 4), 3 + Math.floor(f / 4)],
    hash: firstHash + Math.floor(f / 16), corners: [],
  }));
  return { frames: frames.map((f) => f.frame), fps: 30, model: { weights: 0, q: 2, parts, frames } };
}

// Until no request is open (the stream fetches the next parts as each one arrives).
async function settle(s) {
  for (let i = 0; i < 400 && (i < 2 || s.window.inFlight.size); i++) await new Promise((r) => setTimeout(r, 2));
}

function standIn({ missing = new Set(), busyOnce = new Set() } = {}) {
  const requested = [];
  const fetch = async (url) => {
    const name = url.replace(/^stream\//, '');
    requested.push(name);
    if (busyOnce.delete(name)) return new Response('busy', { status: 503 });
    return missing.has(name) ? new Response('no', { status: 404 }) : new Response(PART, { status: 200 });
  };
  return { fetch, requested };
}

const fileOf = (s, p) => s.model.parts[p].file;
const noWait = { sleep: async () => {}, random: () => 0 };

test('the parts are fetched in playing order from the playhead, each once, within the byte budget', async () => {
  const n = 200;
  const m = manifest(n);
  // room for 12 parts besides the decoded frames: 3 (the most a frame decodes: 15 anchors of 2) x 64 bytes x 3
  const reserve = 3 * DECODED_BYTES_PER_SLOT * 30;
  const { fetch, requested } = standIn();
  const s = new ModelStream('stream/', m, null, { fetch, budgetBytes: reserve + 12 * 4 * VALUES });
  assert.equal(s.decodedReserve, reserve);
  s.setPlayhead(100);
  await settle(s);
  // the parts of frames 100, 101, ... in their order, no part twice, up to 12 parts
  const order = [];
  for (let f = 100; order.length < 12; f++) for (const p of s._partsOf(f)) if (!order.includes(p) && order.length < 12) order.push(p);
  assert.deepEqual(requested, order.map((p) => fileOf(s, p)));
  assert.deepEqual(requested.slice(0, 5), ['weights.bin', 'anchors_static.bin', 'anchors_kf_25.bin', 'anchors_kf_26.bin', 'hash_seg_6.bin']);
  const mem = s.memory();
  assert.equal(mem.heldChunks, 12);
  assert.ok(mem.heldBytes <= mem.windowBudgetBytes && mem.windowBudgetBytes === 12 * 4 * VALUES);
  s.setPlayhead(0);  // a seek: the parts behind are dropped, and the shared ones kept (not fetched again)
  await settle(s);
  assert.ok(![...s.window.items.keys()].some((p) => fileOf(s, p) === 'anchors_kf_25.bin'));
  assert.equal(requested.filter((f) => f === 'weights.bin').length, 1);
  assert.ok(s.memory().heldBytes <= s.memory().windowBudgetBytes);
  assert.equal(s.units, n);
  assert.deepEqual(s.locate(7), { chunk: 7, local: 0 });
});

test('played through, the parts held stay within the budget and hold the playing frame\'s', async () => {
  const n = 64;
  const { fetch } = standIn();
  const s = new ModelStream('stream/', manifest(n), null, { fetch, budgetBytes: 1, wrap: false, maxChunks: 2 });
  // a budget and a part count too small to decode a frame are raised to the playing frame's and the next's
  const most = Math.max(...Array.from({ length: n }, (_, f) => new Set([...s._partsOf(f), ...s._partsOf((f + 1) % n)]).size));
  assert.equal(s.budgetBytes, s.decodedReserve + most * 4 * VALUES);
  assert.equal(s.budgetBytes, s.minimumBytes);
  assert.equal(s.memory().maxChunks, most);
  for (let f = 0; f < n; f += 3) {
    s.setPlayhead(f);
    await settle(s);
    for (const p of s._partsOf(f)) assert.notEqual(s.window.peek(p), undefined, `frame ${f}: ${fileOf(s, p)} held`);
    assert.ok(s.memory().heldBytes <= s.memory().windowBudgetBytes);
  }
  assert.ok(s.memory().peakHeldBytes <= s.memory().windowBudgetBytes);
  assert.ok(s.fetchedBytes > 0 && s.memory().downloads > s.model.parts.length / 2);
});

test('a part fetch is retried through the shared fetcher, and a missing one is the failure of the frames that need it', async () => {
  const { fetch, requested } = standIn({ missing: new Set(['anchors_kf_3.bin']), busyOnce: new Set(['anchors_kf_1.bin']) });
  const errors = [], retries = [];
  const s = new ModelStream('stream/', manifest(40), null, {
    fetch, ...noWait, onError: (e) => errors.push(e.message), onRetry: (file, attempt) => retries.push([file, attempt]),
  });
  s.setPlayhead(0);
  await assert.rejects(Promise.all(s._partsOf(9).map((p) => s.window.get(p))), /anchors_kf_3\.bin is missing \(HTTP 404\)/);
  assert.match(s.failure(9).error.message, /anchors_kf_3\.bin/);
  assert.equal(s.failure(9).retryAt, Infinity);  // missing: fetched again only when asked for
  assert.equal(s.failure(0), undefined);  // frame 0 needs keyframes 0 and 1 only
  assert.equal(errors.length, 1);
  assert.deepEqual(retries, [['anchors_kf_1.bin', 1]]);  // HTTP 503 once: tried again, and held
  await settle(s);
  assert.equal(requested.filter((f) => f === 'anchors_kf_1.bin').length, 2);
  for (const p of s._partsOf(0)) assert.notEqual(s.window.peek(p), undefined);
});
