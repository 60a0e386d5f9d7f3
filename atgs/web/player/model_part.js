// One part file of a model stream (docs/web.md, "A model part file"; written by
// atgs/web/model_format.py): gzip, then "ATGM", u16 version, u16 0, u32 n, n bytes of JSON that
// list the tensors, then their blobs. Every tensor comes back as a Float32Array. Pure logic (no
// DOM, no WebGL) so that Node tests it.

export const MAGIC = 'ATGM';
export const VERSION = 1;
const PREAMBLE_BYTES = 12;
const U16_STEPS = 65535;

// float16 bits -> float32, via a table of the 65536 values (built on first use)
let HALF = null;
function halfTable() {
  if (HALF) return HALF;
  HALF = new Float32Array(65536);
  for (let h = 0; h < 65536; h++) {
    const sign = h & 0x8000 ? -1 : 1, e = (h >> 10) & 0x1f, m = h & 0x3ff;
    HALF[h] = e === 0 ? sign * m * 2 ** -24 : e === 31 ? (m ? NaN : sign * Infinity) : sign * (1 + m / 1024) * 2 ** (e - 15);
  }
  return HALF;
}

// n two-byte values stored as byte planes (every low byte, then every high byte)
function fromPlanes(bytes, n) {
  const out = new Uint16Array(n);
  for (let i = 0; i < n; i++) out[i] = bytes[i] | (bytes[n + i] << 8);
  return out;
}

function tensor(entry, data, where) {
  const shape = entry.shape;
  const n = shape.reduce((a, b) => a * b, 1);
  const cols = shape.length > 1 ? shape.slice(1).reduce((a, b) => a * b, 1) : 1;
  const size = { f32: 4, f16: 2, u16: 2, i8: 1 }[entry.dtype];
  if (!size) throw new Error(`${where}: tensor ${entry.name} has unknown dtype ${entry.dtype}`);
  const start = entry.offset;
  if (start + size * n > data.length) throw new Error(`${where}: tensor ${entry.name} runs past the end (truncated file)`);
  const bytes = data.subarray(start, start + size * n);
  const out = new Float32Array(n);
  if (entry.dtype === 'f32') {
    const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
    for (let i = 0; i < n; i++) out[i] = view.getFloat32(4 * i, true);
  } else if (entry.dtype === 'f16') {
    const table = halfTable(), q = fromPlanes(bytes, n);
    for (let i = 0; i < n; i++) out[i] = table[q[i]];
  } else if (entry.dtype === 'u16') {
    const q = fromPlanes(bytes, n);
    // the reference reader computes lo + q / 65535 (hi - lo) in float64, then rounds to float32
    for (let i = 0; i < n; i++) {
      const c = i % cols, lo = entry.lo[c], hi = entry.hi[c];
      out[i] = lo + (q[i] / U16_STEPS) * (hi - lo);
    }
  } else {
    const scale = entry.scale, groups = scale.length, perGroup = n / groups;
    const q = new Int8Array(bytes.buffer, bytes.byteOffset, n);
    for (let i = 0; i < n; i++) out[i] = Math.fround(q[i] * scale[Math.floor(i / perGroup)][i % cols]);
  }
  return { shape, data: out };
}

/**
 * Parse an inflated part file.
 * @param {Uint8Array} bytes the inflated bytes
 * @param {string} where its URL, for messages
 * @returns {Object<string, {shape: number[], data: Float32Array}>} its tensors by name
 */
export function parsePart(bytes, where = 'part') {
  if (bytes.length < PREAMBLE_BYTES) throw new Error(`${where}: truncated (${bytes.length} bytes)`);
  const magic = String.fromCharCode(bytes[0], bytes[1], bytes[2], bytes[3]);
  if (magic !== MAGIC) throw new Error(`${where}: not a model part file (magic ${JSON.stringify(magic)}, expected "${MAGIC}")`);
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const version = view.getUint16(4, true);
  if (version !== VERSION) throw new Error(`${where}: part version ${version} is not supported (this player reads version ${VERSION})`);
  const n = view.getUint32(8, true);
  if (PREAMBLE_BYTES + n > bytes.length) throw new Error(`${where}: truncated header`);
  let header;
  try {
    header = JSON.parse(new TextDecoder().decode(bytes.subarray(PREAMBLE_BYTES, PREAMBLE_BYTES + n)));
  } catch (e) {
    throw new Error(`${where}: its header is not JSON (${e.message})`);
  }
  const data = bytes.subarray(PREAMBLE_BYTES + n);
  const out = {};
  for (const entry of header.tensors) out[entry.name] = tensor(entry, data, where);
  return out;
}
