// EWA projection of 3D Gaussians and its hand-written backward (no torch dependency).
//
// Mirrors atgs/render/projection.py line by line; the tests compare both. Conventions:
// OpenCV camera, pixel centers at +0.5, Sigma2d = (J Rv R S)(J Rv R S)^T + dilation I with
// gsplat's Jacobian clamp, det via Lagrange's identity (|r1|^2 |r2|^2 - (r1.r2)^2 = |r1 x r2|^2),
// radius = ceil(3 sqrt(lambda_max)), lambda_max = mid + sqrt(max(0.1, mid^2 - det)).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

namespace atgs {

struct Camera {
  float R[9], t[3];  // world-to-camera rotation (row-major) and translation
  float fx, fy, cx, cy;
  float lim_x_neg, lim_x_pos, lim_y_neg, lim_y_pos;  // Jacobian clamp of x/z and y/z
  int width, height;
};

struct ProjectConsts {
  float near, dilation, radius_sigmas, quat_eps, max_radius;
};

inline void quat_to_rot(const float q[4], float R[9]) {
  const float w = q[0], x = q[1], y = q[2], z = q[3];
  R[0] = 1 - 2 * (y * y + z * z); R[1] = 2 * (x * y - w * z);     R[2] = 2 * (x * z + w * y);
  R[3] = 2 * (x * y + w * z);     R[4] = 1 - 2 * (x * x + z * z); R[5] = 2 * (y * z - w * x);
  R[6] = 2 * (x * z - w * y);     R[7] = 2 * (y * z + w * x);     R[8] = 1 - 2 * (x * x + y * y);
}

// Everything the backward pass needs, recomputed from the inputs (cheap, keeps memory low).
struct ProjState {
  float p[3], zs;        // camera-space mean; safe z (1 when culled by the near plane)
  bool in_front, clamp_x, clamp_y;
  float tx, ty;          // clamped x, y used by the Jacobian
  float qn[4], qnorm;    // normalized quaternion and the divisor max(|q|, eps)
  float R[9], M[9];      // rotation, M = R diag(s)
  float A[6];            // A = J Rv (2x3)
  float r1[3], r2[3];    // rows of A M
  float a, b, c, det;    // dilated 2D covariance [[a, b], [b, c]] and its determinant
};

inline void project_one(const float* mean, const float* quat, const float* scale, const Camera& cam,
                        const ProjectConsts& k, ProjState& s) {
  for (int i = 0; i < 3; ++i)
    s.p[i] = cam.R[3 * i] * mean[0] + cam.R[3 * i + 1] * mean[1] + cam.R[3 * i + 2] * mean[2] + cam.t[i];
  s.in_front = s.p[2] > k.near;
  s.zs = s.in_front ? s.p[2] : 1.f;
  const float xz = s.p[0] / s.zs, yz = s.p[1] / s.zs;
  const float cxz = std::min(std::max(xz, -cam.lim_x_neg), cam.lim_x_pos);
  const float cyz = std::min(std::max(yz, -cam.lim_y_neg), cam.lim_y_pos);
  s.clamp_x = !(xz >= -cam.lim_x_neg && xz <= cam.lim_x_pos);
  s.clamp_y = !(yz >= -cam.lim_y_neg && yz <= cam.lim_y_pos);
  s.tx = s.zs * cxz;
  s.ty = s.zs * cyz;
  const float iz = 1.f / s.zs, iz2 = iz * iz;
  const float J[6] = {cam.fx * iz, 0.f, -cam.fx * s.tx * iz2, 0.f, cam.fy * iz, -cam.fy * s.ty * iz2};
  for (int r = 0; r < 2; ++r)
    for (int c = 0; c < 3; ++c)
      s.A[3 * r + c] = J[3 * r] * cam.R[c] + J[3 * r + 1] * cam.R[3 + c] + J[3 * r + 2] * cam.R[6 + c];
  const float n = std::sqrt(quat[0] * quat[0] + quat[1] * quat[1] + quat[2] * quat[2] + quat[3] * quat[3]);
  s.qnorm = std::max(n, k.quat_eps);
  for (int i = 0; i < 4; ++i) s.qn[i] = quat[i] / s.qnorm;
  quat_to_rot(s.qn, s.R);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) s.M[3 * i + j] = s.R[3 * i + j] * scale[j];
  for (int c = 0; c < 3; ++c) {
    s.r1[c] = s.A[0] * s.M[c] + s.A[1] * s.M[3 + c] + s.A[2] * s.M[6 + c];
    s.r2[c] = s.A[3] * s.M[c] + s.A[4] * s.M[3 + c] + s.A[5] * s.M[6 + c];
  }
  const float a0 = s.r1[0] * s.r1[0] + s.r1[1] * s.r1[1] + s.r1[2] * s.r1[2];
  const float c0 = s.r2[0] * s.r2[0] + s.r2[1] * s.r2[1] + s.r2[2] * s.r2[2];
  s.b = s.r1[0] * s.r2[0] + s.r1[1] * s.r2[1] + s.r1[2] * s.r2[2];
  const float x0 = s.r1[1] * s.r2[2] - s.r1[2] * s.r2[1];
  const float x1 = s.r1[2] * s.r2[0] - s.r1[0] * s.r2[2];
  const float x2 = s.r1[0] * s.r2[1] - s.r1[1] * s.r2[0];
  s.a = a0 + k.dilation;
  s.c = c0 + k.dilation;
  s.det = (x0 * x0 + x1 * x1 + x2 * x2) + k.dilation * (a0 + c0) + k.dilation * k.dilation;
}

// Forward outputs of one Gaussian.
inline void project_forward(const float* mean, const float* quat, const float* scale, const Camera& cam,
                            const ProjectConsts& k, float* means2d, float* conic, float* depth,
                            int32_t* radius) {
  ProjState s;
  project_one(mean, quat, scale, cam, k, s);
  conic[0] = s.c / s.det;
  conic[1] = -s.b / s.det;
  conic[2] = s.a / s.det;
  means2d[0] = cam.fx * s.p[0] / s.zs + cam.cx;
  means2d[1] = cam.fy * s.p[1] / s.zs + cam.cy;
  *depth = s.p[2];
  const float mid = 0.5f * (s.a + s.c);
  const float lam = mid + std::sqrt(std::max(mid * mid - s.det, 0.1f));
  const float r = std::min(std::ceil(k.radius_sigmas * std::sqrt(lam)), k.max_radius);
  const float u = means2d[0], v = means2d[1];
  bool visible = s.in_front && u + r > 0 && u - r < cam.width && v + r > 0 && v - r < cam.height;
  visible = visible && std::isfinite(r) && std::isfinite(conic[0]) && std::isfinite(conic[1]) &&
            std::isfinite(conic[2]) && s.det > 0;
  *radius = visible ? int32_t(r) : 0;
}

// Backward of one Gaussian: upstream gradients of means2d (2), conic (3), depth (1).
inline void project_backward(const float* mean, const float* quat, const float* scale, const Camera& cam,
                             const ProjectConsts& k, const float* v_m2, const float* v_con, float v_depth,
                             float* g_mean, float* g_quat, float* g_scale) {
  ProjState s;
  project_one(mean, quat, scale, cam, k, s);
  const float D = k.dilation;
  // conic = (c, -b, a) / det
  const float id = 1.f / s.det;
  const float v_det = -(v_con[0] * s.c - v_con[1] * s.b + v_con[2] * s.a) * id * id;
  const float v_a0 = v_con[2] * id + D * v_det;  // a = a0 + D, and det contains D a0
  const float v_c0 = v_con[0] * id + D * v_det;
  const float v_b = -v_con[1] * id;
  const float x[3] = {s.r1[1] * s.r2[2] - s.r1[2] * s.r2[1], s.r1[2] * s.r2[0] - s.r1[0] * s.r2[2],
                      s.r1[0] * s.r2[1] - s.r1[1] * s.r2[0]};
  const float v_x[3] = {2 * x[0] * v_det, 2 * x[1] * v_det, 2 * x[2] * v_det};
  float v_r1[3], v_r2[3];
  for (int i = 0; i < 3; ++i) {
    v_r1[i] = 2 * s.r1[i] * v_a0 + s.r2[i] * v_b;
    v_r2[i] = 2 * s.r2[i] * v_c0 + s.r1[i] * v_b;
  }
  // x = r1 cross r2: d r1 += r2 cross v_x, d r2 += v_x cross r1
  v_r1[0] += s.r2[1] * v_x[2] - s.r2[2] * v_x[1];
  v_r1[1] += s.r2[2] * v_x[0] - s.r2[0] * v_x[2];
  v_r1[2] += s.r2[0] * v_x[1] - s.r2[1] * v_x[0];
  v_r2[0] += v_x[1] * s.r1[2] - v_x[2] * s.r1[1];
  v_r2[1] += v_x[2] * s.r1[0] - v_x[0] * s.r1[2];
  v_r2[2] += v_x[0] * s.r1[1] - v_x[1] * s.r1[0];
  // rows (r1; r2) = A M: v_A = v_TM M^T, v_M = A^T v_TM
  float v_A[6], v_M[9];
  for (int c = 0; c < 3; ++c) {
    v_A[c] = v_r1[0] * s.M[3 * c] + v_r1[1] * s.M[3 * c + 1] + v_r1[2] * s.M[3 * c + 2];
    v_A[3 + c] = v_r2[0] * s.M[3 * c] + v_r2[1] * s.M[3 * c + 1] + v_r2[2] * s.M[3 * c + 2];
  }
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) v_M[3 * i + j] = s.A[i] * v_r1[j] + s.A[3 + i] * v_r2[j];
  // M = R diag(s)
  float v_R[9];
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      v_R[3 * i + j] = v_M[3 * i + j] * scale[j];
    }
  for (int j = 0; j < 3; ++j) g_scale[j] = v_M[j] * s.R[j] + v_M[3 + j] * s.R[3 + j] + v_M[6 + j] * s.R[6 + j];
  const float w = s.qn[0], qx = s.qn[1], qy = s.qn[2], qz = s.qn[3];
  const float v_qn[4] = {
      2 * (-qz * v_R[1] + qy * v_R[2] + qz * v_R[3] - qx * v_R[5] - qy * v_R[6] + qx * v_R[7]),
      2 * (qy * v_R[1] + qz * v_R[2] + qy * v_R[3] - 2 * qx * v_R[4] - w * v_R[5] + qz * v_R[6] + w * v_R[7] -
           2 * qx * v_R[8]),
      2 * (-2 * qy * v_R[0] + qx * v_R[1] + w * v_R[2] + qx * v_R[3] + qz * v_R[5] - w * v_R[6] + qz * v_R[7] -
           2 * qy * v_R[8]),
      2 * (-2 * qz * v_R[0] - w * v_R[1] + qx * v_R[2] + w * v_R[3] - 2 * qz * v_R[4] + qy * v_R[5] +
           qx * v_R[6] + qy * v_R[7]),
  };
  // q / max(|q|, eps): remove the radial part (only while |q| > eps, else the divisor is constant)
  const float n = std::sqrt(quat[0] * quat[0] + quat[1] * quat[1] + quat[2] * quat[2] + quat[3] * quat[3]);
  const float radial = n > k.quat_eps ? (v_qn[0] * s.qn[0] + v_qn[1] * s.qn[1] + v_qn[2] * s.qn[2] + v_qn[3] * s.qn[3]) : 0.f;
  for (int i = 0; i < 4; ++i) g_quat[i] = (v_qn[i] - radial * s.qn[i]) / s.qnorm;
  // A = J Rv: v_J = v_A Rv^T
  float v_J[6];
  for (int r = 0; r < 2; ++r)
    for (int c = 0; c < 3; ++c)
      v_J[3 * r + c] = v_A[3 * r] * cam.R[3 * c] + v_A[3 * r + 1] * cam.R[3 * c + 1] + v_A[3 * r + 2] * cam.R[3 * c + 2];
  const float iz = 1.f / s.zs, iz2 = iz * iz, iz3 = iz2 * iz;
  float v_zs = -cam.fx * iz2 * v_J[0] - cam.fy * iz2 * v_J[4];
  v_zs += 2 * cam.fx * s.tx * iz3 * v_J[2] + 2 * cam.fy * s.ty * iz3 * v_J[5];
  const float v_tx = -cam.fx * iz2 * v_J[2], v_ty = -cam.fy * iz2 * v_J[5];
  float v_p[3] = {0.f, 0.f, v_depth};
  // tx = zs clamp(x / zs): d/dx = 1 inside the clamp; outside, d/dzs = the clamp limit.
  if (s.clamp_x) v_zs += (s.tx * iz) * v_tx; else v_p[0] += v_tx;
  if (s.clamp_y) v_zs += (s.ty * iz) * v_ty; else v_p[1] += v_ty;
  // means2d = (fx x / zs + cx, fy y / zs + cy)
  v_p[0] += cam.fx * iz * v_m2[0];
  v_p[1] += cam.fy * iz * v_m2[1];
  v_zs += -cam.fx * s.p[0] * iz2 * v_m2[0] - cam.fy * s.p[1] * iz2 * v_m2[1];
  if (s.in_front) v_p[2] += v_zs;
  for (int j = 0; j < 3; ++j) g_mean[j] = cam.R[j] * v_p[0] + cam.R[3 + j] * v_p[1] + cam.R[6 + j] * v_p[2];
}

}  // namespace atgs
