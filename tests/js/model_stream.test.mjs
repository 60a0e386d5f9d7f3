// model_stream.js without a GPU: FrameOfModel's quantization (the chunk's rules) and the parts a
// ModelStream fetches near the playhead, with a stand-in fetch.
import assert from 'node:assert/strict';
import { test } from 'node:test';

import { gzipSync } from 'node:zlib';

import { FrameOfModel, LOOKAHEAD_FRAMES, ModelStream } from '../../atgs/web/player/model_stream.js';

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

test('a decoded frame is quantized over its kept Gaussians, dropped ones at opacity 0', () => {
  const count = 3;
  const decoded = {
    count,
    mean: Float32Array.from([0, 1, 2, 0.9, 10, -5, 4, 0.5, 99, 99, 99, 0]),  // the third is dropped
    quat: Float32Array.from([-1, 0, 0, 0, 0.5, 0.5, 0.5, 0.5, 1, 0, 0, 0]),
    scale: Float32Array.from([0.01, 0.02, 0.04, 1, 0.1, 0.2, 0.3, 1, 5, 5, 5, 0]),
    color: Float32Array.from([0, 0.5, 1, 0, 0.25, 0.75, 0.1, 0, 1, 1, 1, 0]),
  };
  const frame = new FrameOfModel(decoded);
  assert.deepEqual([frame.F, frame.G, frame.S, frame.D], [1, 3, 0, 3]);
  assert.deepEqual(frame.ranges.posMin, [0, -5, 2]);  // the dropped Gaussian's 99s are not in the range
  assert.deepEqual(frame.ranges.posMax, [10, 1, 4]);
  const f = frame.frame(0);
  const r = frame.ranges;
  for (let i = 0; i < 2; i++) {
    for (let c = 0; c < 3; c++) {
      const x = r.posMin[c] + (f.position[4 * i + c] / 65535) * (r.posMax[c] - r.posMin[c]);
      assert.ok(Math.abs(x - decoded.mean[4 * i + c]) <= 0.5 * (r.posMax[c] - r.posMin[c]) / 65535 + 1e-6);
      const s = Math.exp(r.logScaleMin + (f.scaleOpacity[4 * i + c] / 255) * (r.logScaleMax - r.logScaleMin));
      assert.ok(Math.abs(Math.log(s / decoded.scale[4 * i + c])) <= 0.5 * (r.logScaleMax - r.logScaleMin) / 255 + 1e-6);
      assert.equal(f.color[4 * i + c], Math.round(decoded.color[4 * i + c] * 255));
    }
  }
  assert.deepEqual(Array.from(f.scaleOpacity.subarray(0, 12)).filter((_, k) => k % 4 === 3), [229, 128, 0]);
  assert.deepEqual(Array.from(f.rotation.subarray(0, 4)), [127, 0, 0, 0]);  // -q is q: w >= 0
  assert.deepEqual(Array.from(f.rotation.subarray(4, 8)), [64, 64, 64, 64]);
  assert.throws(() => frame.frame(1), RangeError);
});

// A manifest of `n` frames, a keyframe part every 4 frames (a window of two), one hash part.
function manifest(n) {
  const parts = [{ file: 'weights.bin', kind: 'weights', bytes: PART.length }, { file: 'anchors_static.bin', kind: 'anchors', keyframe: -1, bytes: PART.length }];
  const kf = Math.ceil(n / 4) + 1;
  for (let k = 0; k < kf; k++) parts.push({ file: `anchors_kf_${k}.bin`, kind: 'anchors', keyframe: k, bytes: PART.length });
  parts.push({ file: 'hash_seg_0000.bin', kind: 'hash', segment: 0, bytes: PART.length });
  const frames = Array.from({ length: n }, (_, f) => ({ frame: f, segment: 0, anchors: [1, 2 + Math.floor(f / 4), 3 + Math.floor(f / 4)], hash: parts.length - 1, corners: [] }));
  return { frames: frames.map((f) => f.frame), fps: 30, model: { weights: 0, parts, frames } };
}

// Until no request is open (the stream fetches the next parts as each one arrives).
async function settle(s) {
  for (let i = 0; i < 200 && (i < 2 || s.inFlight.size); i++) await new Promise((r) => setTimeout(r, 5));
}

function standIn(missing = new Set()) {
  const requested = [];
  const fetch = async (url) => {
    const name = url.replace(/^stream\//, '');
    requested.push(name);
    return missing.has(name) ? new Response('no', { status: 404 }) : new Response(PART, { status: 200 });
  };
  return { fetch, requested };
}

test('the parts of the frames near the playhead are fetched first, and no others', async () => {
  const n = 200;
  const { fetch, requested } = standIn();
  const s = new ModelStream('stream/', manifest(n), null, { fetch });
  s.setPlayhead(100);
  await settle(s);
  const want = new Set();
  for (let k = 0; k < LOOKAHEAD_FRAMES; k++) for (const p of s._partsOf(100 + k)) want.add(s.model.parts[p].file);
  assert.deepEqual(new Set(requested), want);
  assert.deepEqual(requested.slice(0, 4), ['weights.bin', 'anchors_static.bin', 'anchors_kf_25.bin', 'anchors_kf_26.bin']);
  s.setPlayhead(0);  // a seek: the parts behind are dropped, memory stays bounded
  await settle(s);
  assert.ok(![...s.parts.keys()].some((p) => s.model.parts[p].file === 'anchors_kf_25.bin'));
  assert.equal(s.units, n);
  assert.deepEqual(s.locate(7), { chunk: 7, local: 0 });
});

test('a missing part is the failure of the frames that need it, naming the file', async () => {
  const { fetch } = standIn(new Set(['anchors_kf_3.bin']));
  const errors = [];
  const s = new ModelStream('stream/', manifest(40), null, { fetch, onError: (e) => errors.push(e.message) });
  s.setPlayhead(0);
  await assert.rejects(s.chunk(9), /anchors_kf_3\.bin is missing \(HTTP 404\)/);
  assert.match(s.failed.get(9).message, /anchors_kf_3\.bin/);
  assert.equal(s.failed.get(0), undefined);  // frame 0 needs keyframes 0 and 1 only
  assert.equal(errors.length, 1);
});
