// Back-to-front order of the Gaussians for a view: a 16-bit counting sort of the view depth,
// as the desktop player's radix sort (atgs/viewer/sorting.py). Pure logic, tested by Node. It
// reads a frame's stored positions (quantized or float: the affine map to view depth says which)
// and opacities (frame_layouts.js).

/** Depth levels of the sort key (16 bits). */
export const DEPTH_LEVELS = 65536;

/**
 * The affine map from a quantized position to view depth: z = a[0] qx + a[1] qy + a[2] qz + a[3].
 * @param {ArrayLike<number>} w2c world-to-camera, 16 numbers row-major (OpenCV: z forward)
 * @param {number[]} posMin chunk position minimum (x, y, z)
 * @param {number[]} posMax chunk position maximum
 * @returns {Float64Array} four coefficients
 */
export function depthAffine(w2c, posMin, posMax) {
  const a = new Float64Array(4);
  a[3] = w2c[11];
  for (let c = 0; c < 3; c++) {
    a[c] = (w2c[8 + c] * (posMax[c] - posMin[c])) / 65535;
    a[3] += w2c[8 + c] * posMin[c];
  }
  return a;
}

/**
 * The affine map from a float position to view depth (depthAffine's for positions stored as they are).
 * @param {ArrayLike<number>} w2c world-to-camera, 16 numbers row-major
 * @returns {Float64Array} four coefficients
 */
export function depthAffineOfFloats(w2c) {
  return Float64Array.of(w2c[8], w2c[9], w2c[10], w2c[11]);
}

/**
 * Indices of the Gaussians in front of the near plane whose stored opacity reaches minOpacity,
 * farthest first (ties keep index order). Depths are quantized to 16 bits between the nearest
 * and farthest kept Gaussian, so two Gaussians closer than (zmax - zmin) / 65535 may keep
 * either order, exactly as the desktop player.
 * @param {{count: number, position: ArrayLike<number>, opacity: ArrayLike<number>}} fields position
 *   x, y, z at 4 i (chunk.js FrameFields: quantized; a decoded model frame: float) and the array
 *   holding the opacity at 4 i + 3 (the opacity byte, or the float)
 * @param {Float64Array} affine depthAffine (depthAffineOfFloats) of the view
 * @param {{near: number, minOpacity?: number}} cull near plane; minimum stored opacity (0: keep all)
 * @param {{depth?: Float64Array, kept?: Uint32Array, keys?: Uint16Array, order?: Uint32Array, counts?: Uint32Array}} [scratch]
 *   buffers reused from one call to the next (the returned order is scratch.order)
 * @returns {{order: Uint32Array, count: number}} the first count entries of order are the draw order
 */
export function backToFront(fields, affine, cull, scratch = {}) {
  const n = fields.count;
  const pos = fields.position, so = fields.opacity;
  const minOpacity = cull.minOpacity ?? 0;
  const buffer = (name, Type) => (scratch[name] && scratch[name].length >= n ? scratch[name] : (scratch[name] = new Type(n)));
  const depth = buffer('depth', Float64Array), kept = buffer('kept', Uint32Array);
  const keys = buffer('keys', Uint16Array), order = buffer('order', Uint32Array);
  const counts = scratch.counts ?? (scratch.counts = new Uint32Array(DEPTH_LEVELS + 1));
  counts.fill(0);
  const [ax, ay, az, b] = affine;
  let m = 0, zmin = Infinity, zmax = -Infinity;
  for (let i = 0; i < n; i++) {
    const z = ax * pos[4 * i] + ay * pos[4 * i + 1] + az * pos[4 * i + 2] + b;
    if (!(z > cull.near) || so[4 * i + 3] < minOpacity) continue;
    depth[m] = z;
    kept[m++] = i;
    if (z < zmin) zmin = z;
    if (z > zmax) zmax = z;
  }
  const scale = zmax > zmin ? (DEPTH_LEVELS - 1) / (zmax - zmin) : 0;
  for (let j = 0; j < m; j++) {
    const key = Math.min(DEPTH_LEVELS - 1, Math.max(0, Math.floor((zmax - depth[j]) * scale)));
    keys[j] = key;
    counts[key + 1]++;
  }
  for (let k = 1; k <= DEPTH_LEVELS; k++) counts[k] += counts[k - 1];
  for (let j = 0; j < m; j++) order[counts[keys[j]]++] = kept[j];
  return { order, count: m };
}

/**
 * backToFront with a memory of the last view: sorting again is skipped when neither the view's
 * depth axis nor the frame's positions or opacities (FrameFields.geometryVersion) changed.
 */
export class DepthSorter {
  constructor() {
    this.scratch = {};
    this.last = null;
    this.result = { order: new Uint32Array(0), count: 0 };
    /** True when the last sort() call sorted (false: it reused the previous order). */
    this.sorted = false;
  }

  /**
   * @param {{count: number, position: ArrayLike<number>, opacity: ArrayLike<number>, geometryVersion: number}} fields
   * @param {Float64Array} affine the view's map from a stored position to depth (depthAffine, depthAffineOfFloats)
   * @param {{near: number, minOpacity?: number}} cull
   * @returns {{order: Uint32Array, count: number}}
   */
  sort(fields, affine, cull) {
    const key = [fields, fields.geometryVersion, cull.near, cull.minOpacity ?? 0, ...affine];
    const last = this.last;
    this.sorted = !(last && last.length === key.length && key.every((v, i) => v === last[i]));
    if (this.sorted) {
      this.result = backToFront(fields, affine, cull, this.scratch);
      this.last = key;
    }
    return this.result;
  }
}
