// Reads a byte stream (a response body, an inflating stream) into one Uint8Array. With the size
// expected, into one buffer of that size as the pieces arrive, so a download or an inflation
// never holds all its pieces and their concatenation at once (twice its size); other sizes still
// come out whole, for the caller to report.

/**
 * @param {ReadableStreamDefaultReader<Uint8Array>} reader
 * @param {object} [o]
 * @param {number} [o.expected] bytes the stream should hold
 * @param {(piece: Uint8Array) => void} [o.onPiece] after each piece
 * @returns {Promise<Uint8Array>} every byte read
 */
export async function readAll(reader, { expected, onPiece } = {}) {
  let target = null;
  try {
    if (expected > 0) target = new Uint8Array(expected);
  } catch {
    // a size no buffer can take (a wrong manifest): read the pieces, and let the caller compare sizes
  }
  const parts = [];
  let got = 0;
  for (;;) {
    const { done, value } = await reader.read();
    if (done) break;
    if (target && got + value.length <= target.length) {
      target.set(value, got);
    } else {
      if (target) parts.push(target.subarray(0, got));  // more than expected: whole, the slow way
      target = null;
      parts.push(value);
    }
    got += value.length;
    onPiece?.(value);
  }
  if (target) return got === target.length ? target : target.subarray(0, got);
  if (parts.length === 1) return parts[0];
  const bytes = new Uint8Array(got);
  let offset = 0;
  for (const p of parts) {
    bytes.set(p, offset);
    offset += p.length;
  }
  return bytes;
}
