// sort.js against a plain Array.sort reference.
import assert from 'node:assert/strict';
import { test } from 'node:test';

import { DEPTH_LEVELS, DepthSorter, backToFront, depthAffine, depthAffineOfFloats } from '../../atgs/web/player/sort.js';
import { random } from './encode.mjs';

function randomFields(rand, n) {
  const position = new Uint16Array(4 * n), scaleOpacity = new Uint8Array(4 * n);
  for (let i = 0; i < n; i++) {
    for (let c = 0; c < 3; c++) position[4 * i + c] = Math.floor(rand() * 65536);
    scaleOpacity[4 * i + 3] = Math.floor(rand() * 256);
  }
  return { count: n, position, scaleOpacity, opacity: scaleOpacity, geometryVersion: 1 };
}

// A view from (0, 0, -3) looking along +z, turned a little about y: row 2 of w2c is what counts.
function w2cLookingZ(angle, tz = 3) {
  const c = Math.cos(angle), s = Math.sin(angle);
  return [c, 0, -s, 0, 0, 1, 0, 0, s, 0, c, tz, 0, 0, 0, 1];
}

const ranges = { posMin: [-1, -2, -1], posMax: [1, 2, 1] };

// Reference: world depth of every Gaussian, cull, then the same 16-bit keys sorted by Array.sort.
function reference(fields, w2c, near, minOpacity) {
  const kept = [];
  for (let i = 0; i < fields.count; i++) {
    const p = [0, 1, 2].map((c) => ranges.posMin[c] + (fields.position[4 * i + c] / 65535) * (ranges.posMax[c] - ranges.posMin[c]));
    const z = w2c[8] * p[0] + w2c[9] * p[1] + w2c[10] * p[2] + w2c[11];
    if (z > near && fields.scaleOpacity[4 * i + 3] >= minOpacity) kept.push({ i, z });
  }
  const zmin = Math.min(...kept.map((k) => k.z)), zmax = Math.max(...kept.map((k) => k.z));
  const scale = (DEPTH_LEVELS - 1) / (zmax - zmin);
  for (const k of kept) k.key = Math.min(DEPTH_LEVELS - 1, Math.floor((zmax - k.z) * scale));
  return { kept, order: [...kept].sort((a, b) => a.key - b.key || a.i - b.i).map((k) => k.i) };
}

test('back-to-front order equals Array.sort of the 16-bit depth keys on random data', () => {
  const rand = random(11);
  // [Gaussians, view angle, view z offset, near plane, minimum opacity byte]
  for (const [n, angle, tz, near, minOpacity] of [[1000, 0.3, 0.5, 0.01, 0], [5000, -1.1, 3, 2.5, 1], [50, 2.0, 3, 0.01, 128]]) {
    const fields = randomFields(rand, n);
    const w2c = w2cLookingZ(angle, tz);
    const { order, count } = backToFront(fields, depthAffine(w2c, ranges.posMin, ranges.posMax), { near, minOpacity });
    const ref = reference(fields, w2c, near, minOpacity);
    assert.ok(ref.kept.length > 0 && ref.kept.length < n, 'some Gaussians culled, some kept');
    assert.equal(count, ref.kept.length);
    assert.deepEqual(Array.from(order.subarray(0, count)), ref.order);
    // and the depths fall, up to one key's width
    const z = new Map(ref.kept.map((k) => [k.i, k.z]));
    const zs = ref.order.map((i) => z.get(i));
    const width = (zs[0] - zs[zs.length - 1]) / (DEPTH_LEVELS - 1);
    for (let j = 1; j < zs.length; j++) assert.ok(zs[j] <= zs[j - 1] + width, `depth rises at ${j}`);
  }
});

test('all at one depth keeps index order; none in front gives an empty order', () => {
  const fields = randomFields(random(12), 10);
  for (let i = 0; i < 10; i++) fields.position[4 * i + 2] = 40000;
  const flat = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 3, 0, 0, 0, 1];  // z = world z + 3: x, y do not count
  const { order, count } = backToFront(fields, depthAffine(flat, ranges.posMin, ranges.posMax), { near: 0.01 });
  assert.deepEqual(Array.from(order.subarray(0, count)), [0, 1, 2, 3, 4, 5, 6, 7, 8, 9]);
  const behind = backToFront(fields, depthAffine(w2cLookingZ(0, -10), ranges.posMin, ranges.posMax), { near: 0.01 });
  assert.equal(behind.count, 0);
});

test('DepthSorter sorts again only when the depth axis or the geometry changes', () => {
  const fields = randomFields(random(13), 300);
  const sorter = new DepthSorter();
  const cull = { near: 0.01 };
  const view = w2cLookingZ(0.2);
  sorter.sort(fields, depthAffine(view, ranges.posMin, ranges.posMax), cull);
  assert.equal(sorter.sorted, true);
  sorter.sort(fields, depthAffine(view, ranges.posMin, ranges.posMax), cull);
  assert.equal(sorter.sorted, false);
  const sideways = [...view];
  sideways[3] += 0.5;  // moving along the camera's x axis leaves every depth as it was
  sorter.sort(fields, depthAffine(sideways, ranges.posMin, ranges.posMax), cull);
  assert.equal(sorter.sorted, false);
  sorter.sort(fields, depthAffine(w2cLookingZ(0.21), ranges.posMin, ranges.posMax), cull);
  assert.equal(sorter.sorted, true);
  fields.geometryVersion++;
  sorter.sort(fields, depthAffine(w2cLookingZ(0.21), ranges.posMin, ranges.posMax), cull);
  assert.equal(sorter.sorted, true);
  sorter.sort({ ...fields }, depthAffine(w2cLookingZ(0.21), ranges.posMin, ranges.posMax), cull);  // another chunk's fields
  assert.equal(sorter.sorted, true);
});

test('float positions and opacities (a decoded model frame) sort as their quantized images do', () => {
  // the random quantized fields as floats: the same depths up to rounding, the same culls
  const rand = random(14);
  const q = randomFields(rand, 2000);
  const mean = new Float32Array(4 * q.count);
  for (let i = 0; i < q.count; i++) {
    for (let c = 0; c < 3; c++) mean[4 * i + c] = ranges.posMin[c] + (q.position[4 * i + c] / 65535) * (ranges.posMax[c] - ranges.posMin[c]);
    mean[4 * i + 3] = q.scaleOpacity[4 * i + 3] / 255;
  }
  const floats = { count: q.count, position: mean, opacity: mean, geometryVersion: 0 };
  const w2c = w2cLookingZ(0.7, 1.5);
  const got = backToFront(floats, depthAffineOfFloats(w2c), { near: 0.3, minOpacity: Math.fround(64 / 255) });
  const ref = reference(q, w2c, 0.3, 64);
  assert.ok(ref.kept.length > 0 && ref.kept.length < q.count);
  assert.equal(got.count, ref.kept.length);
  // keys may differ by one where float32 rounding moves a depth across a key boundary
  const z = new Map(ref.kept.map((k) => [k.i, k.z]));
  const zs = Array.from(got.order.subarray(0, got.count), (i) => z.get(i));
  assert.ok(zs.every((d) => d !== undefined), 'the kept Gaussians are the reference\'s');
  const width = (zs[0] - zs[zs.length - 1]) / (DEPTH_LEVELS - 1);
  for (let j = 1; j < zs.length; j++) assert.ok(zs[j] <= zs[j - 1] + 2 * width, `depth rises at ${j}`);
});
