// Cameras in the OpenCV convention of atgs.cameras (x right, y down, z forward; world-to-camera
// 4x4 row-major; pinhole fx fy cx cy with pixel centres at +0.5) and the orbit controls of the
// page. Pure maths (no DOM), tested by Node.

/** gsplat's Jacobian clamp margin (atgs.render.constants.CLAMP_MARGIN). */
export const CLAMP_MARGIN = 0.3;

/** How far zooming out goes, in scene radii from the orbit centre. */
export const MAX_ZOOM_OUT_RADII = 20;

/**
 * Intrinsics {width, height, fx, fy, cx, cy} drawn into a width x height canvas: scaled by
 * one factor (no stretching) so that the camera's whole image fits, centred. A canvas of the
 * camera's aspect ratio gets exactly the camera's intrinsics times width / camera width.
 * @param {{width: number, height: number, fx: number, fy: number, cx: number, cy: number}} intr
 * @param {number} width canvas width in pixels
 * @param {number} height canvas height in pixels
 */
export function fitIntrinsics(intr, width, height) {
  if (width === intr.width && height === intr.height) return { ...intr };
  const s = Math.min(width / intr.width, height / intr.height);
  return {
    width, height,
    fx: intr.fx * s, fy: intr.fy * s,
    cx: intr.cx * s + 0.5 * (width - intr.width * s),
    cy: intr.cy * s + 0.5 * (height - intr.height * s),
  };
}

/**
 * gsplat's Jacobian clamp as atgs.viewer.splat_renderer.clamp_limits: x/z in [-l[0], l[1]],
 * y/z in [-l[2], l[3]].
 * @param {{width: number, height: number, fx: number, fy: number, cx: number, cy: number}} intr
 * @returns {number[]} four limits
 */
export function clampLimits(intr, margin = CLAMP_MARGIN) {
  const tanX = (0.5 * intr.width) / intr.fx, tanY = (0.5 * intr.height) / intr.fy;
  return [
    intr.cx / intr.fx + margin * tanX,
    (intr.width - intr.cx) / intr.fx + margin * tanX,
    intr.cy / intr.fy + margin * tanY,
    (intr.height - intr.cy) / intr.fy + margin * tanY,
  ];
}

/**
 * Pixel coordinates (u, v; row 0 at the top) and view depth z of a world point.
 * @param {ArrayLike<number>} w2c row-major world-to-camera
 * @param {{fx: number, fy: number, cx: number, cy: number}} intr
 * @param {number[]} p world point
 * @returns {number[]} [u, v, z]
 */
export function project(w2c, intr, p) {
  const [x, y, z] = transform(w2c, p);
  return [(intr.fx * x) / z + intr.cx, (intr.fy * y) / z + intr.cy, z];
}

/** w2c applied to a world point (row-major 4x4, affine). */
export function transform(w2c, p) {
  const out = [0, 0, 0];
  for (let r = 0; r < 3; r++) out[r] = w2c[4 * r] * p[0] + w2c[4 * r + 1] * p[1] + w2c[4 * r + 2] * p[2] + w2c[4 * r + 3];
  return out;
}

/** The camera centre in world coordinates: -R^T t. */
export function cameraCenter(w2c) {
  const out = [0, 0, 0];
  for (let c = 0; c < 3; c++) out[c] = -(w2c[c] * w2c[3] + w2c[4 + c] * w2c[7] + w2c[8 + c] * w2c[11]);
  return out;
}

/**
 * The cameras' mean image-up direction (their -y axis) in world coordinates, as
 * atgs.render.environment.up_basis takes it; (0, 0, 1) when there are none or they cancel.
 * @param {{w2c: number[]}[]} cameras
 */
export function upDirection(cameras) {
  const up = [0, 0, 0];
  for (const cam of cameras) for (let c = 0; c < 3; c++) up[c] -= cam.w2c[4 + c];
  const n = Math.hypot(...up);
  return n < 1e-6 * Math.max(1, cameras.length) ? [0, 0, 1] : up.map((v) => v / n);
}

// Rotation matrix (row-major 3x3) of angle a about the unit axis u (right-hand rule).
function axisRotation(u, a) {
  const c = Math.cos(a), s = Math.sin(a), t = 1 - c;
  const [x, y, z] = u;
  return [
    t * x * x + c, t * x * y - s * z, t * x * z + s * y,
    t * x * y + s * z, t * y * y + c, t * y * z - s * x,
    t * x * z - s * y, t * y * z + s * x, t * z * z + c,
  ];
}

/**
 * The page's view: a world-to-camera matrix and the intrinsics of the training camera it
 * started from (scaled to the canvas with fitIntrinsics when drawn). Orbit, pan and zoom move
 * the camera rigidly about `center` and make it "free" (trainingIndex null).
 */
export class ViewCamera {
  /**
   * @param {{center: number[], radius: number, up: number[]}} scene orbit centre, scene radius
   *   (bounds the zoom) and the world up axis orbiting turns about
   */
  constructor(scene) {
    this.center = [...scene.center];
    this.radius = scene.radius > 0 ? scene.radius : 1;
    this.up = [...scene.up];
    this.w2c = new Float64Array([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]);
    this.intrinsics = { width: 1, height: 1, fx: 1, fy: 1, cx: 0.5, cy: 0.5 };
    /** Index of the training camera shown exactly, or null once the view moved. */
    this.trainingIndex = null;
    /** Incremented on every change (a renderer redraws when it differs). */
    this.version = 0;
  }

  /**
   * Show training camera i exactly (its w2c and intrinsics).
   * @param {{width: number, height: number, fx: number, fy: number, cx: number, cy: number, w2c: number[]}} cam
   * @param {number} index
   */
  setTraining(cam, index) {
    if (!cam || cam.w2c.length !== 16) throw new Error(`training camera ${index} has no 4x4 w2c`);
    this.w2c = Float64Array.from(cam.w2c);
    const { width, height, fx, fy, cx, cy } = cam;
    this.intrinsics = { width, height, fx, fy, cx, cy };
    this.trainingIndex = index;
    this.version++;
  }

  // Replace the rotation R (rows of w2c) by R Q and keep the world point `pivot` where it was in camera space.
  _rotateWorld(Q, pivot) {
    const w = this.w2c;
    const R = [w[0], w[1], w[2], w[4], w[5], w[6], w[8], w[9], w[10]];
    for (let r = 0; r < 3; r++) {
      let moved = w[4 * r + 3];  // t + R pivot - (R Q) pivot
      for (let c = 0; c < 3; c++) {
        let rq = 0;
        for (let k = 0; k < 3; k++) rq += R[3 * r + k] * Q[3 * k + c];
        w[4 * r + c] = rq;
        moved += (R[3 * r + c] - rq) * pivot[c];
      }
      w[4 * r + 3] = moved;
    }
  }

  _moved() {
    this.trainingIndex = null;
    this.version++;
  }

  /**
   * Turn the scene about the centre: yaw about the up axis, then pitch about the camera's x
   * axis (the front of the scene follows the pointer). Stops short of the poles.
   * @param {number} yaw radians (positive: the scene's front moves right)
   * @param {number} pitch radians (positive: the scene's front moves down)
   */
  orbit(yaw, pitch) {
    this._rotateWorld(axisRotation(this.up, yaw), this.center);
    const w = this.w2c;
    const xAxis = [w[0], w[1], w[2]];
    const Q = axisRotation(xAxis, pitch);
    // forward (row 2 of R) after the pitch is row 2 of R Q; keep it 5 degrees off the up axis
    let cosUp = 0;
    for (let c = 0; c < 3; c++) cosUp += (w[8] * Q[c] + w[9] * Q[3 + c] + w[10] * Q[6 + c]) * this.up[c];
    if (Math.abs(cosUp) < Math.cos((5 * Math.PI) / 180)) this._rotateWorld(Q, this.center);
    this._moved();
  }

  /**
   * Slide the camera (and the orbit centre with it) so that the scene at the centre's depth
   * follows the pointer by (dx, dy) canvas pixels.
   * @param {number} dx pixels, right
   * @param {number} dy pixels, down
   * @param {{fx: number, fy: number}} intr the intrinsics the canvas is drawn with
   */
  pan(dx, dy, intr) {
    let depth = transform(this.w2c, this.center)[2];
    if (!(depth > 1e-6)) depth = this.radius;
    const d = [(dx * depth) / intr.fx, (dy * depth) / intr.fy];
    const w = this.w2c;
    w[3] += d[0];
    w[7] += d[1];
    for (let c = 0; c < 3; c++) this.center[c] -= w[c] * d[0] + w[4 + c] * d[1];  // - R^T (dx', dy', 0)
    this._moved();
  }

  /**
   * Move the camera towards (factor < 1) or away from (factor > 1) the centre, no nearer than
   * 0.001 scene radii and no farther than MAX_ZOOM_OUT_RADII (or where it is, if farther
   * already): beyond that the scene is a dot and a wheel spun on finds no way back.
   * @param {number} factor distance multiplier
   */
  zoom(factor) {
    const C = cameraCenter(this.w2c);
    const dist = Math.max(Math.hypot(C[0] - this.center[0], C[1] - this.center[1], C[2] - this.center[2]), 1e-12);
    const farthest = Math.max(dist, MAX_ZOOM_OUT_RADII * this.radius);
    const f = Math.min(Math.max(factor, (1e-3 * this.radius) / dist), farthest / dist);
    const Cn = C.map((v, c) => this.center[c] + (v - this.center[c]) * f);
    const w = this.w2c;
    for (let r = 0; r < 3; r++) w[4 * r + 3] = -(w[4 * r] * Cn[0] + w[4 * r + 1] * Cn[1] + w[4 * r + 2] * Cn[2]);
    this._moved();
  }
}
