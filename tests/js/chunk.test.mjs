// chunk.js against chunks written from docs/web.md by the fixture encode.mjs.
import assert from 'node:assert/strict';
import { test } from 'node:test';

import { inflate, parseChunk } from '../../atgs/web/player/chunk.js';
import { encodeChunk, gzip, random, randomRecord } from './encode.mjs';

// The records of Gaussian i in fields (chunk.js FrameFields), as the fixture's Record.
function recordAt(fields, i) {
  const at = (a) => Array.from(a.subarray(4 * i, 4 * i + 4));
  const p = at(fields.position), so = at(fields.scaleOpacity), c = at(fields.color);
  return { p: p.slice(0, 3), s: so.slice(0, 3), r: at(fields.rotation), o: so[3], c: c.slice(0, 3) };
}

function records(fields) {
  return Array.from({ length: fields.count }, (_, i) => recordAt(fields, i));
}

// F frames of G Gaussians, the first S static, the rest moving at random; Gaussian S's x
// position crosses 256 up and back down (a carry and a borrow between the byte planes).
function movingChunk(seed, F, G, S) {
  const rand = random(seed);
  const statics = Array.from({ length: S }, () => randomRecord(rand));
  const frames = [];
  for (let k = 0; k < F; k++) frames.push([...statics, ...Array.from({ length: G - S }, () => randomRecord(rand))]);
  const crossing = [250, 256, 255, 511, 65535, 0];
  for (let k = 0; k < F; k++) frames[k][S].p[0] = crossing[k % crossing.length];
  return { S, frames };
}

test('round trip through gzip: every frame, forward, backward and at random', async () => {
  const spec = movingChunk(1, 6, 37, 11);
  const chunk = parseChunk(await inflate(gzip(encodeChunk(spec))));
  assert.equal(chunk.F, 6);
  assert.equal(chunk.G, 37);
  assert.equal(chunk.S, 11);
  assert.equal(chunk.D, 26);
  for (const order of [[0, 1, 2, 3, 4, 5], [5, 4, 3, 2, 1, 0], [3, 0, 5, 2, 2, 4, 1]]) {
    for (const k of order) assert.deepEqual(records(chunk.frame(k)), spec.frames[k], `frame ${k}`);
  }
});

test('a u16 crossing a 256 boundary between frames keeps its high byte', async () => {
  const spec = movingChunk(2, 6, 5, 2);
  const chunk = parseChunk(encodeChunk(spec));
  const xs = [0, 1, 2, 3, 4, 5].map((k) => chunk.frame(k).position[4 * 2]);
  assert.deepEqual(xs, [250, 256, 255, 511, 65535, 0]);
});

test('ranges come from the header', () => {
  const spec = { ...movingChunk(3, 2, 4, 1), posMin: [-2, 0.5, 3], posMax: [4, 1.5, 9], logScaleMin: -7.25, logScaleMax: 0.5 };
  const { ranges } = parseChunk(encodeChunk(spec));
  assert.deepEqual(ranges, { posMin: [-2, 0.5, 3], posMax: [4, 1.5, 9], logScaleMin: -7.25, logScaleMax: 0.5 });
});

test('static block only (D = 0) and dynamic blocks only (S = 0)', () => {
  const rand = random(4);
  const still = Array.from({ length: 9 }, () => randomRecord(rand));
  const allStatic = parseChunk(encodeChunk({ S: 9, frames: [still, still, still] }));
  assert.equal(allStatic.D, 0);
  for (const k of [2, 0, 1]) assert.deepEqual(records(allStatic.frame(k)), still);

  const allDynamic = movingChunk(5, 3, 8, 0);
  const chunk = parseChunk(encodeChunk(allDynamic));
  assert.equal(chunk.S, 0);
  for (const k of [0, 1, 2]) assert.deepEqual(records(chunk.frame(k)), allDynamic.frames[k]);
});

test('static Gaussians stay put and are stored once', () => {
  const spec = movingChunk(6, 4, 20, 15);
  const bytes = encodeChunk(spec);
  assert.equal(bytes.length, 48 + 17 * 15 + 4 * 17 * 5);
  const chunk = parseChunk(bytes);
  for (let k = 0; k < 4; k++) assert.deepEqual(records(chunk.frame(k)).slice(0, 15), spec.frames[0].slice(0, 15));
});

test('playing forward applies one delta block per frame', () => {
  const chunk = parseChunk(encodeChunk(movingChunk(7, 6, 10, 3)));
  const read = [];
  const block = chunk.block.bind(chunk);
  chunk.block = (k) => {
    read.push(k);
    return block(k);
  };
  for (let k = 0; k < 6; k++) chunk.frame(k);
  assert.deepEqual(read, [0, 1, 2, 3, 4, 5]);
  chunk.frame(5);  // the frame held: nothing to read
  assert.deepEqual(read, [0, 1, 2, 3, 4, 5]);
});

test('geometryVersion changes only when a position or an opacity changes', () => {
  const rand = random(8);
  const a = Array.from({ length: 4 }, () => randomRecord(rand));
  const recolored = a.map((r) => ({ ...r, c: [1, 2, 3], s: [9, 9, 9] }));
  const moved = recolored.map((r, i) => (i === 3 ? { ...r, p: [r.p[0] ^ 1, r.p[1], r.p[2]] } : r));
  const faded = moved.map((r, i) => (i === 2 ? { ...r, o: r.o ^ 1 } : r));
  const chunk = parseChunk(encodeChunk({ S: 0, frames: [a, recolored, moved, faded] }));
  const v = [0, 1, 2, 3].map((k) => chunk.frame(k).geometryVersion);
  assert.equal(v[1], v[0]);
  assert.notEqual(v[2], v[1]);
  assert.notEqual(v[3], v[2]);
  assert.notEqual(chunk.frame(1).geometryVersion, v[3]);  // going back restarts: a new version
});

test('errors: bad magic, version, truncation, sizes that do not add up, bad gzip', async () => {
  const good = encodeChunk(movingChunk(9, 3, 6, 2));
  const patched = (offset, bytes) => {
    const b = good.slice();
    b.set(bytes, offset);
    return b;
  };
  assert.throws(() => parseChunk(patched(0, [0x50, 0x4b, 3, 4])), /not an ATGS chunk \(magic "PK\\u0003\\u0004", expected "ATGC"\)/);
  assert.throws(() => parseChunk(patched(4, [2, 0])), /chunk version 2 is not supported/);
  assert.throws(() => parseChunk(good.subarray(0, good.length - 1)), new RegExp(`truncated chunk: ${good.length - 1} of ${good.length} bytes`));
  assert.throws(() => parseChunk(good.subarray(0, 20)), /truncated chunk: 20 bytes, shorter than the 48-byte header/);
  assert.throws(() => parseChunk(new Uint8Array([...good, 0])), /chunk sizes do not add up/);
  assert.throws(() => parseChunk(patched(12, [7, 0, 0, 0])), /7 static Gaussians of 6/);
  assert.throws(() => parseChunk(patched(6, [0, 0])), /holds no frames/);
  assert.throws(() => parseChunk(good).frame(3), RangeError);
  const gz = gzip(good);
  await assert.rejects(inflate(gz.subarray(0, gz.length - 10)), /not valid gzip data/);
  await assert.rejects(inflate(good), /not valid gzip data/);
});
