// Test fixture (not shipped): writes chunk files and stream folders per docs/web.md, written
// from the spec independently of atgs/web/player/chunk.js so the tests check the reader
// against the layout, not against itself.

import { gzipSync } from 'node:zlib';

/**
 * A quantized Gaussian: p (3 x u16), s (3 x u8 log-scale), r (4 x i8 w, x, y, z), o (u8), c (3 x u8).
 * @typedef {{p: number[], s: number[], r: number[], o: number, c: number[]}} Record
 */

// The planar block of records: each component's n values (a u16 as its low bytes, then its high bytes).
function block(records) {
  const n = records.length;
  const out = new Uint8Array(17 * n);
  let at = 0;
  const plane = (get) => {
    for (const rec of records) out[at++] = get(rec) & 0xff;
  };
  for (let c = 0; c < 3; c++) {
    plane((r) => r.p[c]);
    plane((r) => r.p[c] >> 8);
  }
  for (let c = 0; c < 3; c++) plane((r) => r.s[c]);
  for (let c = 0; c < 4; c++) plane((r) => r.r[c]);  // & 0xff: an i8's two's complement byte
  plane((r) => r.o);
  for (let c = 0; c < 3; c++) plane((r) => r.c[c]);
  return out;
}

/**
 * The inflated bytes of a chunk.
 * @param {{S: number, frames: Record[][], posMin?: number[], posMax?: number[],
 *          logScaleMin?: number, logScaleMax?: number}} spec frames[k] lists the G records of
 *   frame k; the first S must be the same in every frame
 * @returns {Uint8Array}
 */
export function encodeChunk({ S, frames, posMin = [-1, -1, -1], posMax = [1, 1, 1], logScaleMin = -5, logScaleMax = 0 }) {
  const F = frames.length, G = frames[0].length;
  for (const f of frames) {
    if (f.length !== G) throw new Error('every frame needs the same Gaussians');
    for (let i = 0; i < S; i++) {
      if (JSON.stringify(f[i]) !== JSON.stringify(frames[0][i])) throw new Error(`Gaussian ${i} is not static`);
    }
  }
  const header = new Uint8Array(48);
  const v = new DataView(header.buffer);
  header.set([0x41, 0x54, 0x47, 0x43]);  // "ATGC"
  v.setUint16(4, 1, true);
  v.setUint16(6, F, true);
  v.setUint32(8, G, true);
  v.setUint32(12, S, true);
  [...posMin, ...posMax, logScaleMin, logScaleMax].forEach((x, k) => v.setFloat32(16 + 4 * k, x, true));
  const parts = [header, block(frames[0].slice(0, S))];
  let previous = null;
  for (const f of frames) {
    const values = block(f.slice(S));
    if (previous === null) {
      parts.push(values);
    } else {
      parts.push(values.map((b, i) => (b - previous[i]) & 0xff));  // per byte plane, modulo 256
    }
    previous = values;
  }
  const out = new Uint8Array(parts.reduce((n, p) => n + p.length, 0));
  let at = 0;
  for (const p of parts) {
    out.set(p, at);
    at += p.length;
  }
  return out;
}

/** gzip as the exporter writes it (level 9). */
export function gzip(bytes) {
  return new Uint8Array(gzipSync(bytes, { level: 9 }));
}

/** A deterministic pseudo-random generator (mulberry32): rand() in [0, 1). */
export function random(seed) {
  let a = seed >>> 0;
  return () => {
    a = (a + 0x6d2b79f5) >>> 0;
    let t = a;
    t = Math.imul(t ^ (t >>> 15), t | 1);
    t ^= t + Math.imul(t ^ (t >>> 7), t | 61);
    return ((t ^ (t >>> 14)) >>> 0) / 4294967296;
  };
}

/** A random quantized record. */
export function randomRecord(rand) {
  const int = (lo, hi) => lo + Math.floor(rand() * (hi - lo + 1));
  return {
    p: [int(0, 65535), int(0, 65535), int(0, 65535)],
    s: [int(0, 255), int(0, 255), int(0, 255)],
    r: [int(0, 127), int(-127, 127), int(-127, 127), int(-127, 127)],
    o: int(0, 255),
    c: [int(0, 255), int(0, 255), int(0, 255)],
  };
}

/**
 * A stream folder in memory: {files: Map(name -> Uint8Array), manifest}. chunks: one list of
 * frames (Record[][]) plus S per chunk.
 */
export function encodeStream(chunks, { chunkFrames, cameras = [], fps = 30 } = {}) {
  const files = new Map();
  const entries = chunks.map((c, i) => {
    const bytes = gzip(encodeChunk(c));
    const file = `chunk_${String(i).padStart(6, '0')}.bin`;
    files.set(file, bytes);
    return { file, frames: c.frames.length, gaussians: c.frames[0].length, static: c.S, bytes: bytes.length };
  });
  const frames = chunks.flatMap((c) => c.frames).map((_, i) => i);
  const manifest = {
    format: 'atgs-web', version: 1, fps, frames, chunk_frames: chunkFrames ?? chunks[0].frames.length,
    chunks: entries, cameras, background: [0, 0, 0], environment: null,
    render: { near: 0.01, dilation: 0.3, alpha_min: 1 / 255, alpha_max: 0.99, extent: 3.0 },
    scene: { center: [0, 0, 0], radius: 1 },
  };
  files.set('manifest.json', new TextEncoder().encode(JSON.stringify(manifest)));
  return { files, manifest };
}
