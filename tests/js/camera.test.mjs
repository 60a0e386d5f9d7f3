// camera.js against hand-computed cases.
import assert from 'node:assert/strict';
import { test } from 'node:test';

import { MAX_ZOOM_OUT_RADII, ViewCamera, cameraCenter, clampLimits, fitIntrinsics, project, transform, upDirection } from '../../atgs/web/player/camera.js';

const close = (a, b, tol = 1e-9) => {
  assert.equal(a.length, b.length);
  a.forEach((v, i) => assert.ok(Math.abs(v - b[i]) <= tol, `[${i}] ${v} != ${b[i]}`));
};

// A camera at (4, 0, 0) looking at the origin along -x, image y along world -z (world z is up):
// the rows of R are the camera axes in world coordinates (x = y cross z: a rotation).
const R = [[0, 1, 0], [0, 0, -1], [-1, 0, 0]];
const C = [4, 0, 0];
const t = R.map((row) => -(row[0] * C[0] + row[1] * C[1] + row[2] * C[2]));
const W2C = [...R[0], t[0], ...R[1], t[1], ...R[2], t[2], 0, 0, 0, 1];
const CAM = { name: 'cam', width: 320, height: 240, fx: 300, fy: 310, cx: 161, cy: 118.5, w2c: W2C };

test('projection of known points through a training camera', () => {
  close(cameraCenter(W2C), C);
  // origin: 4 in front, on the principal point
  close(project(W2C, CAM, [0, 0, 0]), [161, 118.5, 4]);
  // world +y is the camera's +x: 1 unit at depth 4 is fx / 4 pixels right
  close(project(W2C, CAM, [0, 1, 0]), [161 + 300 / 4, 118.5, 4]);
  // world +z (up) is the camera's -y: above the centre, a smaller row
  close(project(W2C, CAM, [2, 0, 0.5]), [161, 118.5 - (310 * 0.5) / 2, 2]);
  close(transform(W2C, [0, 0, -1]), [0, 1, 4]);
});

test('a training camera is shown exactly; its intrinsics scale with the canvas', () => {
  const view = new ViewCamera({ center: [0, 0, 0], radius: 1, up: [0, 0, 1] });
  view.setTraining(CAM, 3);
  assert.deepEqual(Array.from(view.w2c), W2C);
  assert.equal(view.trainingIndex, 3);
  assert.deepEqual(fitIntrinsics(view.intrinsics, 320, 240), { width: 320, height: 240, fx: 300, fy: 310, cx: 161, cy: 118.5 });
  // twice the size: every intrinsic doubles (pixel edges scale, centres stay at +0.5)
  assert.deepEqual(fitIntrinsics(view.intrinsics, 640, 480), { width: 640, height: 480, fx: 600, fy: 620, cx: 322, cy: 237 });
  // a wider canvas: scaled by the height, the image centred (80 px margins left and right)
  assert.deepEqual(fitIntrinsics(view.intrinsics, 800, 480), { width: 800, height: 480, fx: 600, fy: 620, cx: 402, cy: 237 });
});

test('clamp limits as atgs.viewer.splat_renderer.clamp_limits', () => {
  const K = { width: 320, height: 240, fx: 300, fy: 310, cx: 161, cy: 118.5 };
  const tx = 160 / 300, ty = 120 / 310;
  close(clampLimits(K), [161 / 300 + 0.3 * tx, 159 / 300 + 0.3 * tx, 118.5 / 310 + 0.3 * ty, 121.5 / 310 + 0.3 * ty]);
});

test('orbit keeps the distance to the centre, turns the front the way of the pointer, stops at the pole', () => {
  const center = [0.3, -0.2, 0.1];
  const view = new ViewCamera({ center, radius: 1, up: [0, 0, 1] });
  view.setTraining(CAM, 0);
  const dist = () => Math.hypot(...cameraCenter(view.w2c).map((v, i) => v - center[i]));
  const d0 = dist();
  const front = [2, 0, 0];  // between the camera and the centre
  const u0 = project(view.w2c, CAM, front);
  view.orbit(0.1, 0);
  const u1 = project(view.w2c, CAM, front);
  assert.ok(u1[0] > u0[0], 'yaw > 0: the front moves right');
  view.orbit(0, 0.1);
  assert.ok(project(view.w2c, CAM, front)[1] > u1[1], 'pitch > 0: the front moves down');
  for (let k = 0; k < 50; k++) view.orbit(0.37, -0.21);
  assert.ok(Math.abs(dist() - d0) < 1e-9, 'distance kept');
  // R stays a rotation
  const w = view.w2c;
  const rows = [0, 1, 2].map((r) => [w[4 * r], w[4 * r + 1], w[4 * r + 2]]);
  for (let a = 0; a < 3; a++) for (let b = 0; b < 3; b++) {
    const dot = rows[a][0] * rows[b][0] + rows[a][1] * rows[b][1] + rows[a][2] * rows[b][2];
    assert.ok(Math.abs(dot - (a === b ? 1 : 0)) < 1e-9);
  }
  assert.equal(view.trainingIndex, null);
  // pitching far past the pole stops 5 degrees short of it
  for (let k = 0; k < 100; k++) view.orbit(0, 0.05);
  const forwardUp = Math.abs(view.w2c[10]);
  assert.ok(forwardUp <= Math.cos((5 * Math.PI) / 180) + 1e-9, `forward . up = ${forwardUp}`);
});

test('pan keeps the centre under the pointer; zoom scales its distance', () => {
  const view = new ViewCamera({ center: [0, 0, 0], radius: 1, up: [0, 0, 1] });
  view.setTraining(CAM, 0);
  const c0 = project(view.w2c, CAM, [0, 0, 0]);
  view.pan(12, -7, CAM);
  close(project(view.w2c, CAM, [0, 0, 0]), [c0[0] + 12, c0[1] - 7, 4]);  // the scene followed the pointer
  close(project(view.w2c, CAM, view.center), c0);                        // the orbit centre moved with the view
  const before = Math.hypot(...cameraCenter(view.w2c).map((v, i) => v - view.center[i]));
  view.zoom(0.5);
  const after = Math.hypot(...cameraCenter(view.w2c).map((v, i) => v - view.center[i]));
  close([after], [before * 0.5]);
  close(project(view.w2c, CAM, view.center).slice(0, 2), c0.slice(0, 2));
});

test('up direction is the mean of the cameras\' -y axes', () => {
  close(upDirection([{ w2c: W2C }]), [0, 0, 1]);
  close(upDirection([]), [0, 0, 1]);
});

test('zoom stops 0.001 radii from the centre and MAX_ZOOM_OUT_RADII away from it', () => {
  const view = new ViewCamera({ center: [0, 0, 0], radius: 2, up: [0, 0, 1] });
  view.setTraining(CAM, 0);  // 4 from the centre
  const dist = () => Math.hypot(...cameraCenter(view.w2c));
  view.zoom(1e-9);
  close([dist()], [2e-3]);
  view.zoom(1e9);
  close([dist()], [MAX_ZOOM_OUT_RADII * 2], 1e-9);
  // a view already beyond the limit may come closer, never go farther
  const far = new ViewCamera({ center: [0, 0, 0], radius: 0.1, up: [0, 0, 1] });
  far.setTraining(CAM, 0);
  far.zoom(3);
  close([Math.hypot(...cameraCenter(far.w2c))], [4]);
  far.zoom(0.5);
  close([Math.hypot(...cameraCenter(far.w2c))], [2]);
});
