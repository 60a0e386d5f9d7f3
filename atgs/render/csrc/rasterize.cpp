// Tile-based CPU rasterizer of 2D Gaussians (forward and hand-written backward).
//
// Conventions follow SPEC section 2 and atgs/render/reference.py exactly:
//   sigma = 0.5 (a dx^2 + c dy^2) + b dx dy,  dx = u - (x + 0.5),  dy = v - (y + 0.5)
//   a pixel is skipped if sigma < 0 or sigma > sigma_cutoff (the 3-sigma ellipse),
//   alpha = min(alpha_max, o exp(-sigma)), skipped if alpha < alpha_min,
//   front to back, stop (excluding that Gaussian) when T (1 - alpha) < t_min,
//   out = sum_i f_i alpha_i T_i + T_final bg  for C feature channels (RGB, view depth z and z^2;
//   z^2 gives the spread of depth along each ray, which the depth-distortion loss needs).
// Every pixel sees the same Gaussians in the same order whatever the tile size, because the
// cut-off is a per-pixel test; tiles and per-Gaussian boxes only skip work.
//
// Parallelism: OpenMP over tiles (dynamic schedule: tiles differ a lot in cost). Within a tile
// the loop runs Gaussian-outer / pixel-inner over the box where the Gaussian can be
// non-negligible, 8 pixels per SIMD vector, keeping per-pixel state in local arrays; the
// per-pixel order is still front to back. The backward pass writes one gradient
// record per (tile, Gaussian) pair and reduces them serially, so results are deterministic.
// Narrow includes (not <torch/extension.h>): they cut the first-use compile time by more than half.
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/csrc/utils/pybind.h>

#include "projection.h"

#include <omp.h>

#if defined(__AVX__)
#include <immintrin.h>
#endif

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <numeric>
#include <vector>

namespace {

constexpr int kChannels = 5;  // RGB, view depth, squared view depth
constexpr int kTile = 16;  // tile edge in pixels; rows are processed as whole SIMD vectors
constexpr int kTilePix = kTile * kTile;
constexpr int64_t kParallelProjectMin = 65536;  // smaller inputs: a fork-join costs more than it saves
constexpr int kGradStride = 6 + kChannels;  // mean(2) conic(3) opacity(1) features(5)

// 8-lane vectors (GCC/Clang vector extensions): AVX2 when compiled with -mavx2, two SSE
// registers otherwise. A tile row of 16 pixels is two of them; lanes are masked, not looped.
typedef float v8f __attribute__((vector_size(32)));
typedef int32_t v8i __attribute__((vector_size(32)));

inline v8f splat(float x) { return v8f{x, x, x, x, x, x, x, x}; }
inline v8i splati(int32_t x) { return v8i{x, x, x, x, x, x, x, x}; }
inline v8f vmin(v8f a, v8f b) { return a < b ? a : b; }
inline v8f vmax(v8f a, v8f b) { return a > b ? a : b; }
inline v8f select(v8i m, v8f a, v8f b) { return m ? a : b; }
// Lane mask as bits (lane l -> bit l); one instruction with AVX, a lane loop otherwise.
inline int movemask(v8i m) {
#if defined(__AVX__)
  return _mm256_movemask_ps(reinterpret_cast<__m256>(m));
#else
  int r = 0;
  for (int l = 0; l < 8; ++l) r |= (m[l] != 0) << l;
  return r;
#endif
}
inline bool any(v8i m) { return movemask(m) != 0; }
inline int count(v8i m) { return __builtin_popcount(unsigned(movemask(m))); }
inline float hsum(v8f a) {
#if defined(__AVX__)
  const __m256 v = reinterpret_cast<__m256>(a);
  __m128 x = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
  x = _mm_add_ps(x, _mm_movehl_ps(x, x));
  x = _mm_add_ss(x, _mm_shuffle_ps(x, x, 1));
  return _mm_cvtss_f32(x);
#else
  float r = 0.f;
  for (int l = 0; l < 8; ++l) r += a[l];
  return r;
#endif
}

// exp(-s) for s in [0, 4.5] on 8 lanes, branch-free: exp(-s) = 2^-n exp(y), n = round(s / ln 2),
// |y| <= ln(2)/2, degree-6 Taylor polynomial (relative error < 2e-7 against std::exp).
inline v8f exp_neg(v8f s) {
  const v8f t = s * 1.44269504f;
  const v8i n = __builtin_convertvector(t + 0.5f, v8i);
  const v8f y = __builtin_convertvector(n, v8f) * 0.693147181f - s;
  v8f q = splat(1.f / 720.f);
  q = q * y + 1.f / 120.f;
  q = q * y + 1.f / 24.f;
  q = q * y + 1.f / 6.f;
  q = q * y + 0.5f;
  q = q * y + 1.f;
  q = q * y + 1.f;
  const v8i bits = (127 - n) << 23;
  return q * reinterpret_cast<const v8f&>(bits);
}

struct Params {
  float alpha_max, alpha_min, t_min, sigma_cutoff;
  int width, height, tile, channels, threads;
  int tiles_x() const { return (width + tile - 1) / tile; }
  int tiles_y() const { return (height + tile - 1) / tile; }
};

// Inclusive pixel box outside which Gaussian g cannot pass the sigma and alpha_min tests.
struct Box {
  int x0, x1, y0, y1;
  bool empty() const { return x0 > x1 || y0 > y1; }
};

Box gaussian_box(const float* m2, const float* con, float opacity, const Params& p) {
  Box none{1, 0, 1, 0};
  if (!(opacity >= p.alpha_min)) return none;
  // alpha >= alpha_min  <=>  sigma <= log(o / alpha_min); never beyond the 3-sigma cut-off.
  float lim = std::min(p.sigma_cutoff, std::log(opacity / p.alpha_min));
  if (lim < 0.f) return none;
  const double a = con[0], b = con[1], c = con[2];
  const double det = a * c - b * b;
  if (!(det > 0.0)) return none;
  // The ellipse sigma <= lim has half-extents sqrt(2 lim Sigma_xx), Sigma = conic^-1.
  // Slightly enlarged: the box only has to contain every pixel that passes the tests.
  const double ex = std::sqrt(2.0 * lim * c / det) * 1.0001 + 1e-3;
  const double ey = std::sqrt(2.0 * lim * a / det) * 1.0001 + 1e-3;
  const double u = m2[0], v = m2[1];
  double fx0 = std::ceil(u - ex - 0.5), fx1 = std::floor(u + ex - 0.5);
  double fy0 = std::ceil(v - ey - 0.5), fy1 = std::floor(v + ey - 0.5);
  fx0 = std::max(fx0, 0.0);
  fy0 = std::max(fy0, 0.0);
  fx1 = std::min(fx1, double(p.width - 1));
  fy1 = std::min(fy1, double(p.height - 1));
  if (!(fx0 <= fx1 && fy0 <= fy1)) return none;
  return Box{int(fx0), int(fx1), int(fy0), int(fy1)};
}

struct Binning {
  std::vector<Box> boxes;          // per Gaussian
  std::vector<int64_t> offsets;    // per tile, size n_tiles + 1
  std::vector<int32_t> ids;        // Gaussian ids, front to back within each tile
  // The same pairs numbered Gaussian by Gaussian (depth order): slots[k] is the number of list
  // entry k, and Gaussian order[j] owns slots first[j] .. first[j+1]-1. The backward pass stores
  // its per-pair gradients by slot, so the final reduction reads them sequentially.
  std::vector<int32_t> slots, order;
  std::vector<int64_t> first;
};

Binning bin_gaussians(const float* means2d, const float* conics, const float* opac,
                      const float* depths, const int32_t* radii, int64_t n, const Params& p) {
  Binning bins;
  bins.boxes.resize(n);
  // Sort keys: depth bits (depths of visible Gaussians are > 0, so their IEEE bits order like the
  // floats) above the index. Unique keys sort exactly like a stable sort by depth.
  std::vector<uint64_t> keys;
  keys.reserve(n);
  for (int64_t i = 0; i < n; ++i) {
    bins.boxes[i] = radii[i] > 0 ? gaussian_box(means2d + 2 * i, conics + 3 * i, opac[i], p)
                                 : Box{1, 0, 1, 0};
    if (bins.boxes[i].empty()) continue;
    uint32_t bits;
    std::memcpy(&bits, depths + i, sizeof(bits));
    keys.push_back((uint64_t(bits) << 32) | uint64_t(i));
  }
  std::sort(keys.begin(), keys.end());
  std::vector<Box> sorted(keys.size());  // boxes in depth order: sequential access below
  for (size_t j = 0; j < keys.size(); ++j) sorted[j] = bins.boxes[uint32_t(keys[j])];
  const int tx = p.tiles_x();
  bins.offsets.assign(int64_t(tx) * p.tiles_y() + 1, 0);
  for (const Box& b : sorted)
    for (int y = b.y0 / kTile; y <= b.y1 / kTile; ++y)
      for (int x = b.x0 / kTile; x <= b.x1 / kTile; ++x) bins.offsets[int64_t(y) * tx + x + 1]++;
  std::partial_sum(bins.offsets.begin(), bins.offsets.end(), bins.offsets.begin());
  bins.ids.resize(bins.offsets.back());
  bins.slots.resize(bins.offsets.back());
  bins.order.resize(keys.size());
  bins.first.resize(keys.size() + 1);
  std::vector<int64_t> cursor(bins.offsets.begin(), bins.offsets.end() - 1);
  int32_t slot = 0;
  for (size_t j = 0; j < keys.size(); ++j) {
    const Box& b = sorted[j];
    const int32_t g = int32_t(uint32_t(keys[j]));
    bins.order[j] = g;
    bins.first[j] = slot;
    for (int y = b.y0 / kTile; y <= b.y1 / kTile; ++y)
      for (int x = b.x0 / kTile; x <= b.x1 / kTile; ++x) {
        const int64_t pos = cursor[int64_t(y) * tx + x]++;
        bins.ids[pos] = g;
        bins.slots[pos] = slot++;
      }
  }
  bins.first[keys.size()] = slot;
  return bins;
}

Params make_params(int64_t width, int64_t height, int64_t tile, int64_t channels, int64_t threads,
                   double alpha_max, double alpha_min, double t_min, double sigma_cutoff) {
  TORCH_CHECK(channels == kChannels, "expected 5 feature channels (RGB, depth, depth^2)");
  TORCH_CHECK(tile == kTile, "the kernel is compiled for 16x16 tiles");
  return Params{float(alpha_max), float(alpha_min), float(t_min), float(sigma_cutoff),
                int(width), int(height), int(tile), int(channels), int(std::max<int64_t>(1, threads))};
}

void check_input(const at::Tensor& t, const char* name, at::ScalarType type) {
  TORCH_CHECK(t.device().is_cpu(), name, " must be a CPU tensor");
  TORCH_CHECK(t.scalar_type() == type, name, " has the wrong dtype");
  TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
}

}  // namespace

// Returns image (H,W,3), alpha (H,W), depth (H,W), depth_sq (H,W), T_final (H,W), last (H,W) int32 (per-pixel
// count of list entries used), tile offsets (n_tiles+1) int64, tile ids (pairs) int32,
// slots / order / first int32 / int32 / int64 (see Binning), stats
// int64 (blended pixel-Gaussian pairs, tile-Gaussian pairs). Depth and its square are the 4th and
// 5th blended channels (background 0); depth is also the sort key. All outputs are written here, serially per tile, so no
// extra torch ops (each a fork-join on a busy machine) are needed around the kernel.
std::vector<at::Tensor> forward(at::Tensor means2d, at::Tensor conics, at::Tensor opacities,
                                   at::Tensor colors, at::Tensor depths, at::Tensor radii,
                                   at::Tensor background, int64_t width, int64_t height,
                                   int64_t tile, int64_t threads, double alpha_max, double alpha_min,
                                   double t_min, double sigma_cutoff) {
  for (auto& [t, name] : {std::pair{means2d, "means2d"}, {conics, "conics"}, {opacities, "opacities"},
                          {colors, "colors"}, {depths, "depths"}, {background, "background"}})
    check_input(t, name, at::kFloat);
  check_input(radii, "radii", at::kInt);
  TORCH_CHECK(colors.size(1) == 3 && background.numel() == 3, "expected RGB colors and background");
  const int64_t n = means2d.size(0);
  const Params p = make_params(width, height, tile, kChannels, threads, alpha_max, alpha_min, t_min, sigma_cutoff);
  const float* m2 = means2d.data_ptr<float>();
  const float* con = conics.data_ptr<float>();
  const float* op = opacities.data_ptr<float>();
  const float* col = colors.data_ptr<float>();
  const float* dep = depths.data_ptr<float>();
  const float bg[kChannels] = {background.data_ptr<float>()[0], background.data_ptr<float>()[1],
                               background.data_ptr<float>()[2], 0.f, 0.f};
  Binning bins = bin_gaussians(m2, con, op, dep, radii.data_ptr<int32_t>(), n, p);

  auto image = at::empty({height, width, 3}, means2d.options());
  auto alpha_out = at::empty({height, width}, means2d.options());
  auto depth_out = at::empty({height, width}, means2d.options());
  auto depth_sq_out = at::empty({height, width}, means2d.options());
  auto t_final = at::empty({height, width}, means2d.options());
  auto last = at::empty({height, width}, radii.options());
  float* img_p = image.data_ptr<float>();
  float* al_p = alpha_out.data_ptr<float>();
  float* dp_p = depth_out.data_ptr<float>();
  float* dq_p = depth_sq_out.data_ptr<float>();
  float* tf_p = t_final.data_ptr<float>();
  int32_t* last_p = last.data_ptr<int32_t>();
  const int tx = p.tiles_x(), n_tiles = p.tiles_x() * p.tiles_y();
  std::vector<int64_t> tile_blended(n_tiles, 0);

  const v8f lane_x0 = {0.5f, 1.5f, 2.5f, 3.5f, 4.5f, 5.5f, 6.5f, 7.5f};
  const v8i lane_i0 = {0, 1, 2, 3, 4, 5, 6, 7};

#pragma omp parallel for schedule(dynamic, 1) num_threads(p.threads)
  for (int t = 0; t < n_tiles; ++t) {
    const int px0 = (t % tx) * kTile, py0 = (t / tx) * kTile;
    const int pw = std::min(kTile, p.width - px0), ph = std::min(kTile, p.height - py0);
    const int64_t begin = bins.offsets[t], end = bins.offsets[t + 1];
    // Per-pixel state: row y, half h (pixels 8h .. 8h+7) -> index 2y + h; planar channels.
    v8f T[2 * kTile], acc[kChannels][2 * kTile];
    v8i stop[2 * kTile];
    for (int r = 0; r < 2 * kTile; ++r) {
      T[r] = splat(1.f);
      stop[r] = splati(int32_t(end - begin));
      for (int ch = 0; ch < kChannels; ++ch) acc[ch][r] = splat(0.f);
    }
    int n_done = 0;
    int64_t blended = 0;  // (Gaussian, pixel) pairs composited in this tile, for benchmarks
    const int n_pix = pw * ph;
    for (int64_t k = begin; k < end && n_done < n_pix; ++k) {
      const int32_t g = bins.ids[k];
      const Box& b = bins.boxes[g];
      const float ca = con[3 * g], cb = con[3 * g + 1], cc = con[3 * g + 2], o = op[g];
      const float f[kChannels] = {col[3 * g], col[3 * g + 1], col[3 * g + 2], dep[g], dep[g] * dep[g]};
      const int x0 = std::max(b.x0, px0) - px0, x1 = std::min(b.x1, px0 + pw - 1) - px0;
      const int y0 = std::max(b.y0, py0) - py0, y1 = std::min(b.y1, py0 + ph - 1) - py0;
      const int32_t idx = int32_t(k - begin);
      const float ux = m2[2 * g] - float(px0), vy = m2[2 * g + 1] - float(py0);
      for (int y = y0; y <= y1; ++y) {
        const float dy = vy - (float(y) + 0.5f);
        for (int h = x0 / 8; h <= x1 / 8; ++h) {
          const int r = 2 * y + h;
          const v8f dx = ux - (lane_x0 + float(8 * h));
          const v8i xi = lane_i0 + 8 * h;
          const v8f sigma = 0.5f * (ca * dx * dx + cc * dy * dy) + cb * dx * dy;
          const v8i inside = (xi >= x0) & (xi <= x1) & (stop[r] > idx) & (sigma >= 0.f) & (sigma <= p.sigma_cutoff);
          if (!any(inside)) continue;  // cheap test first: skips exp() outside the ellipse
          const v8f alpha = vmin(splat(p.alpha_max), o * exp_neg(vmin(vmax(sigma, splat(0.f)), splat(p.sigma_cutoff))));
          const v8i live = inside & (alpha >= p.alpha_min);
          const v8f next_T = T[r] * (1.f - alpha);
          const v8i low = next_T < p.t_min;
          const v8i halt = live & low, use = live & ~low;
          if (any(halt)) {
            stop[r] = halt ? splati(idx) : stop[r];
            n_done += count(halt);
          }
          const v8f w = select(use, alpha * T[r], splat(0.f));
          blended += count(use);
          for (int ch = 0; ch < kChannels; ++ch) acc[ch][r] += f[ch] * w;
          T[r] = select(use, next_T, T[r]);
        }
      }
    }
    for (int y = 0; y < ph; ++y)
      for (int x = 0; x < pw; ++x) {
        const int r = 2 * y + x / 8, l = x % 8;
        const int64_t pix = int64_t(py0 + y) * p.width + (px0 + x);
        for (int ch = 0; ch < 3; ++ch) img_p[pix * 3 + ch] = acc[ch][r][l] + T[r][l] * bg[ch];
        dp_p[pix] = acc[3][r][l];
        dq_p[pix] = acc[4][r][l];
        al_p[pix] = 1.f - T[r][l];
        tf_p[pix] = T[r][l];
        last_p[pix] = stop[r][l];
      }
    tile_blended[t] = blended;
  }
  auto offsets = at::empty({int64_t(bins.offsets.size())}, at::kLong);
  auto ids = at::empty({int64_t(bins.ids.size())}, at::kInt);
  std::copy(bins.offsets.begin(), bins.offsets.end(), offsets.data_ptr<int64_t>());
  std::copy(bins.ids.begin(), bins.ids.end(), ids.data_ptr<int32_t>());
  auto slots = at::empty({int64_t(bins.slots.size())}, at::kInt);
  auto order = at::empty({int64_t(bins.order.size())}, at::kInt);
  auto first = at::empty({int64_t(bins.first.size())}, at::kLong);
  std::copy(bins.slots.begin(), bins.slots.end(), slots.data_ptr<int32_t>());
  std::copy(bins.order.begin(), bins.order.end(), order.data_ptr<int32_t>());
  std::copy(bins.first.begin(), bins.first.end(), first.data_ptr<int64_t>());
  const int64_t total_blended = std::accumulate(tile_blended.begin(), tile_blended.end(), int64_t(0));
  auto stats = at::empty({2}, at::kLong);
  stats.data_ptr<int64_t>()[0] = total_blended;
  stats.data_ptr<int64_t>()[1] = int64_t(bins.ids.size());
  return {image, alpha_out, depth_out, depth_sq_out, t_final, last, offsets, ids, slots, order, first, stats};
}

// Gradients w.r.t. means2d (N,2), conics (N,3), opacities (N,), colors (N,3), depths (N,) (through
// both the depth and the depth^2 channel), background (3,).
std::vector<at::Tensor> backward(at::Tensor means2d, at::Tensor conics, at::Tensor opacities,
                                    at::Tensor colors, at::Tensor depths, at::Tensor radii,
                                    at::Tensor background, at::Tensor t_final, at::Tensor last,
                                    at::Tensor offsets, at::Tensor ids, at::Tensor slots, at::Tensor order,
                                    at::Tensor first, at::Tensor grad_image,
                                    at::Tensor grad_alpha, at::Tensor grad_depth, at::Tensor grad_depth_sq,
                                    int64_t width, int64_t height, int64_t tile, int64_t threads,
                                    double alpha_max, double alpha_min, double t_min, double sigma_cutoff) {
  for (auto& [t, name] : {std::pair{means2d, "means2d"}, {conics, "conics"}, {opacities, "opacities"},
                          {colors, "colors"}, {depths, "depths"}, {background, "background"},
                          {t_final, "t_final"}})
    check_input(t, name, at::kFloat);
  // Upstream gradients may be strided (e.g. expanded by sum()): read them through their strides
  // instead of paying for a contiguous copy.
  for (auto& [t, name] : {std::pair{grad_image, "grad_image"}, {grad_alpha, "grad_alpha"}, {grad_depth, "grad_depth"},
                          {grad_depth_sq, "grad_depth_sq"}}) {
    TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == at::kFloat, name, " must be a CPU float32 tensor");
    TORCH_CHECK(t.size(0) == height && t.size(1) == width, name, " has the wrong shape");
  }
  check_input(radii, "radii", at::kInt);
  check_input(last, "last", at::kInt);
  check_input(offsets, "offsets", at::kLong);
  check_input(ids, "ids", at::kInt);
  check_input(slots, "slots", at::kInt);
  check_input(order, "order", at::kInt);
  check_input(first, "first", at::kLong);
  const int32_t* slot_p = slots.data_ptr<int32_t>();
  const int32_t* order_p = order.data_ptr<int32_t>();
  const int64_t* first_p = first.data_ptr<int64_t>();
  const int64_t n_sorted = order.size(0);
  const int64_t n = means2d.size(0);
  const Params p = make_params(width, height, tile, kChannels, threads, alpha_max, alpha_min, t_min, sigma_cutoff);
  const float* m2 = means2d.data_ptr<float>();
  const float* con = conics.data_ptr<float>();
  const float* op = opacities.data_ptr<float>();
  const float* col = colors.data_ptr<float>();
  const float* dep = depths.data_ptr<float>();
  const float bg[kChannels] = {background.data_ptr<float>()[0], background.data_ptr<float>()[1],
                               background.data_ptr<float>()[2], 0.f, 0.f};
  const float* tf_p = t_final.data_ptr<float>();
  const int32_t* last_p = last.data_ptr<int32_t>();
  const int64_t* off = offsets.data_ptr<int64_t>();
  const int32_t* id_p = ids.data_ptr<int32_t>();
  const float* gi = grad_image.data_ptr<float>();
  const float* ga = grad_alpha.data_ptr<float>();
  const float* gd = grad_depth.data_ptr<float>();
  const float* gq = grad_depth_sq.data_ptr<float>();
  const int64_t si_y = grad_image.stride(0), si_x = grad_image.stride(1), si_c = grad_image.stride(2);
  const int64_t sa_y = grad_alpha.stride(0), sa_x = grad_alpha.stride(1);
  const int64_t sd_y = grad_depth.stride(0), sd_x = grad_depth.stride(1);
  const int64_t sq_y = grad_depth_sq.stride(0), sq_x = grad_depth_sq.stride(1);
  const int64_t n_pairs = ids.size(0);
  const int tx = p.tiles_x(), n_tiles = p.tiles_x() * p.tiles_y();
  TORCH_CHECK(offsets.size(0) == n_tiles + 1, "offsets do not match the image size");

  // Boxes are recomputed exactly as in the forward pass (same inputs, same code).
  std::vector<Box> boxes(n);
  for (int64_t i = 0; i < n; ++i)
    boxes[i] = radii.data_ptr<int32_t>()[i] > 0 ? gaussian_box(m2 + 2 * i, con + 3 * i, op[i], p)
                                                 : Box{1, 0, 1, 0};
  std::vector<float> pair_grads(n_pairs * kGradStride, 0.f);
  std::vector<double> tile_bg(int64_t(n_tiles) * kChannels, 0.0);

  const v8f lane_x0 = {0.5f, 1.5f, 2.5f, 3.5f, 4.5f, 5.5f, 6.5f, 7.5f};
  const v8i lane_i0 = {0, 1, 2, 3, 4, 5, 6, 7};

#pragma omp parallel for schedule(dynamic, 1) num_threads(p.threads)
  for (int t = 0; t < n_tiles; ++t) {
    const int px0 = (t % tx) * kTile, py0 = (t / tx) * kTile;
    const int pw = std::min(kTile, p.width - px0), ph = std::min(kTile, p.height - py0);
    const int64_t begin = off[t], end = off[t + 1];
    v8f T[2 * kTile], Tf[2 * kTile], bgterm[2 * kTile], B[kChannels][2 * kTile], G[kChannels][2 * kTile];
    v8i stop[2 * kTile];
    int32_t max_stop = 0;
    for (int r = 0; r < 2 * kTile; ++r) {  // lanes outside the image stay inert (stop = 0)
      T[r] = Tf[r] = splat(1.f);
      bgterm[r] = splat(0.f);
      stop[r] = splati(0);
      for (int ch = 0; ch < kChannels; ++ch) B[ch][r] = G[ch][r] = splat(0.f);
    }
    for (int y = 0; y < ph; ++y)
      for (int x = 0; x < pw; ++x) {
        const int r = 2 * y + x / 8, l = x % 8;
        const int64_t pix = int64_t(py0 + y) * p.width + (px0 + x);
        const float tf = tf_p[pix];
        T[r][l] = Tf[r][l] = tf;
        stop[r][l] = last_p[pix];
        max_stop = std::max(max_stop, last_p[pix]);
        // d loss / d T_final = bg . g - g_alpha  (alpha_out = 1 - T_final)
        const int64_t py = py0 + y, px = px0 + x;
        float s = -ga[py * sa_y + px * sa_x];
        for (int ch = 0; ch < kChannels; ++ch) {
          const float gch = ch < 3    ? gi[py * si_y + px * si_x + ch * si_c]
                            : ch == 3 ? gd[py * sd_y + px * sd_x]
                                      : gq[py * sq_y + px * sq_x];
          G[ch][r][l] = gch;
          s += bg[ch] * gch;
          tile_bg[int64_t(t) * kChannels + ch] += double(tf) * gch;
        }
        bgterm[r][l] = s * tf;
      }
    // Entries at or after every pixel's stop index contributed nothing: start below them.
    for (int64_t k = std::min(end, begin + max_stop) - 1; k >= begin; --k) {
      const int32_t g = id_p[k];
      const Box& b = boxes[g];
      const float ca = con[3 * g], cb = con[3 * g + 1], cc = con[3 * g + 2], o = op[g];
      const float f[kChannels] = {col[3 * g], col[3 * g + 1], col[3 * g + 2], dep[g], dep[g] * dep[g]};
      const int x0 = std::max(b.x0, px0) - px0, x1 = std::min(b.x1, px0 + pw - 1) - px0;
      const int y0 = std::max(b.y0, py0) - py0, y1 = std::min(b.y1, py0 + ph - 1) - py0;
      const int32_t idx = int32_t(k - begin);
      const float ux = m2[2 * g] - float(px0), vy = m2[2 * g + 1] - float(py0);
      const v8f zero = splat(0.f);
      v8f gu = zero, gv = zero, gA = zero, gB = zero, gC = zero, gO = zero;
      v8f gf[kChannels] = {zero, zero, zero, zero, zero};
      for (int y = y0; y <= y1; ++y) {
        const float dy = vy - (float(y) + 0.5f);
        for (int h = x0 / 8; h <= x1 / 8; ++h) {
          const int r = 2 * y + h;
          const v8f dx = ux - (lane_x0 + float(8 * h));
          const v8i xi = lane_i0 + 8 * h;
          const v8f sigma = 0.5f * (ca * dx * dx + cc * dy * dy) + cb * dx * dy;
          const v8i inside = (xi >= x0) & (xi <= x1) & (stop[r] > idx) & (sigma >= 0.f) & (sigma <= p.sigma_cutoff);
          if (!any(inside)) continue;  // cheap test first: skips exp() outside the ellipse
          const v8f e = exp_neg(vmin(vmax(sigma, zero), splat(p.sigma_cutoff)));
          const v8f raw = o * e;
          const v8f alpha = vmin(splat(p.alpha_max), raw);
          const v8i live = inside & (alpha >= p.alpha_min);
          const v8f ra = 1.f / vmax(splat(1e-6f), 1.f - alpha);
          const v8f Ti = T[r] * ra;  // transmittance in front of this Gaussian
          const v8f w = select(live, alpha * Ti, zero);
          v8f dalpha = -bgterm[r] * ra;
          for (int ch = 0; ch < kChannels; ++ch) {
            dalpha += (f[ch] * Ti - B[ch][r] * ra) * G[ch][r];
            gf[ch] += w * G[ch][r];
            B[ch][r] += f[ch] * w;
          }
          T[r] = select(live, Ti, T[r]);
          const v8f da = select(live & (raw <= p.alpha_max), dalpha, zero);  // clamped alpha: no gradient
          gO += e * da;
          const v8f vs = -raw * da;  // d loss / d sigma
          gA += 0.5f * vs * dx * dx;
          gB += vs * dx * dy;
          gC += 0.5f * vs * dy * dy;
          gu += vs * (ca * dx + cb * dy);
          gv += vs * (cb * dx + cc * dy);
        }
      }
      float* rec = pair_grads.data() + int64_t(slot_p[k]) * kGradStride;
      rec[0] = hsum(gu); rec[1] = hsum(gv); rec[2] = hsum(gA); rec[3] = hsum(gB); rec[4] = hsum(gC);
      rec[5] = hsum(gO);
      for (int ch = 0; ch < kChannels; ++ch) rec[6 + ch] = hsum(gf[ch]);
    }
  }

  // Gaussian-major slots: each Gaussian's pair records are contiguous, summed in a fixed order
  // (deterministic) and written once. Outputs are not created with torch::zeros: each torch op
  // is a fork-join of its thread pool, costly on a busy machine.
  auto g_m2 = at::empty({n, 2}, means2d.options());
  auto g_con = at::empty({n, 3}, means2d.options());
  auto g_op = at::empty({n}, means2d.options());
  auto g_col = at::empty({n, 3}, means2d.options());
  auto g_dep = at::empty({n}, means2d.options());
  auto g_bg = at::empty({3}, means2d.options());
  float *pm = g_m2.data_ptr<float>(), *pc = g_con.data_ptr<float>(), *po = g_op.data_ptr<float>(),
        *pf = g_col.data_ptr<float>(), *pd = g_dep.data_ptr<float>();
  std::fill(pm, pm + 2 * n, 0.f);
  std::fill(pc, pc + 3 * n, 0.f);
  std::fill(po, po + n, 0.f);
  std::fill(pf, pf + 3 * n, 0.f);
  std::fill(pd, pd + n, 0.f);
  for (int64_t j = 0; j < n_sorted; ++j) {
    float a[kGradStride] = {};
    for (int64_t q = first_p[j]; q < first_p[j + 1]; ++q) {
      const float* r = pair_grads.data() + q * kGradStride;
      for (int i = 0; i < kGradStride; ++i) a[i] += r[i];
    }
    const int64_t g = order_p[j];
    pm[2 * g] = a[0]; pm[2 * g + 1] = a[1];
    pc[3 * g] = a[2]; pc[3 * g + 1] = a[3]; pc[3 * g + 2] = a[4];
    po[g] = a[5];
    pf[3 * g] = a[6]; pf[3 * g + 1] = a[7]; pf[3 * g + 2] = a[8];
    pd[g] = a[9] + 2.f * dep[g] * a[10];  // d(z^2)/dz = 2z
  }
  for (int ch = 0; ch < 3; ++ch) {
    double s = 0.0;
    for (int t = 0; t < n_tiles; ++t) s += tile_bg[int64_t(t) * kChannels + ch];
    g_bg.data_ptr<float>()[ch] = float(s);
  }
  return {g_m2, g_con, g_op, g_col, g_dep, g_bg};
}

namespace {

// consts = (near, dilation, clamp_margin, radius_sigmas, quat_eps, max_radius)
atgs::Camera make_camera(const at::Tensor& viewmat, const at::Tensor& K, int64_t width, int64_t height,
                         double clamp_margin) {
  check_input(viewmat, "viewmat", at::kFloat);
  check_input(K, "K", at::kFloat);
  const float* V = viewmat.data_ptr<float>();
  const float* k = K.data_ptr<float>();
  atgs::Camera cam;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) cam.R[3 * i + j] = V[4 * i + j];
    cam.t[i] = V[4 * i + 3];
  }
  cam.fx = k[0];
  cam.fy = k[4];
  cam.cx = k[2];
  cam.cy = k[5];
  const float m = float(clamp_margin);
  const float tan_x = 0.5f * float(width) / cam.fx, tan_y = 0.5f * float(height) / cam.fy;
  cam.lim_x_neg = cam.cx / cam.fx + m * tan_x;
  cam.lim_x_pos = (float(width) - cam.cx) / cam.fx + m * tan_x;
  cam.lim_y_neg = cam.cy / cam.fy + m * tan_y;
  cam.lim_y_pos = (float(height) - cam.cy) / cam.fy + m * tan_y;
  cam.width = int(width);
  cam.height = int(height);
  return cam;
}

atgs::ProjectConsts make_consts(const std::vector<double>& c) {
  TORCH_CHECK(c.size() == 6, "expected 6 projection constants");
  return atgs::ProjectConsts{float(c[0]), float(c[1]), float(c[3]), float(c[4]), float(c[5])};
}

}  // namespace

// Returns means2d (N,2), conics (N,3), depths (N,), radii (N,) int32.
std::vector<at::Tensor> project_fwd(at::Tensor means, at::Tensor quats, at::Tensor scales,
                                       at::Tensor viewmat, at::Tensor K, int64_t width, int64_t height,
                                       int64_t threads, std::vector<double> consts) {
  for (auto& [t, name] : {std::pair{means, "means"}, {quats, "quats"}, {scales, "scales"}})
    check_input(t, name, at::kFloat);
  const atgs::Camera cam = make_camera(viewmat, K, width, height, consts.at(2));
  const atgs::ProjectConsts k = make_consts(consts);
  const int64_t n = means.size(0);
  auto m2 = at::empty({n, 2}, means.options());
  auto con = at::empty({n, 3}, means.options());
  auto dep = at::empty({n}, means.options());
  auto rad = at::empty({n}, means.options().dtype(at::kInt));
  const float *pm = means.data_ptr<float>(), *pq = quats.data_ptr<float>(), *ps = scales.data_ptr<float>();
  float *o_m2 = m2.data_ptr<float>(), *o_con = con.data_ptr<float>(), *o_dep = dep.data_ptr<float>();
  int32_t* o_rad = rad.data_ptr<int32_t>();
#pragma omp parallel for schedule(static) num_threads(int(std::max<int64_t>(1, threads))) if (n > kParallelProjectMin)
  for (int64_t i = 0; i < n; ++i)
    atgs::project_forward(pm + 3 * i, pq + 4 * i, ps + 3 * i, cam, k, o_m2 + 2 * i, o_con + 3 * i, o_dep + i,
                          o_rad + i);
  return {m2, con, dep, rad};
}

// Gradients w.r.t. means (N,3), quats (N,4), scales (N,3).
std::vector<at::Tensor> project_bwd(at::Tensor means, at::Tensor quats, at::Tensor scales,
                                       at::Tensor viewmat, at::Tensor K, int64_t width, int64_t height,
                                       int64_t threads, std::vector<double> consts, at::Tensor v_means2d,
                                       at::Tensor v_conics, at::Tensor v_depths) {
  for (auto& [t, name] : {std::pair{means, "means"}, {quats, "quats"}, {scales, "scales"},
                          {v_means2d, "v_means2d"}, {v_conics, "v_conics"}, {v_depths, "v_depths"}})
    check_input(t, name, at::kFloat);
  const atgs::Camera cam = make_camera(viewmat, K, width, height, consts.at(2));
  const atgs::ProjectConsts k = make_consts(consts);
  const int64_t n = means.size(0);
  auto g_means = at::empty({n, 3}, means.options());
  auto g_quats = at::empty({n, 4}, means.options());
  auto g_scales = at::empty({n, 3}, means.options());
  const float *pm = means.data_ptr<float>(), *pq = quats.data_ptr<float>(), *ps = scales.data_ptr<float>();
  const float *vm = v_means2d.data_ptr<float>(), *vc = v_conics.data_ptr<float>(), *vd = v_depths.data_ptr<float>();
  float *gm = g_means.data_ptr<float>(), *gq = g_quats.data_ptr<float>(), *gs = g_scales.data_ptr<float>();
#pragma omp parallel for schedule(static) num_threads(int(std::max<int64_t>(1, threads))) if (n > kParallelProjectMin)
  for (int64_t i = 0; i < n; ++i)
    atgs::project_backward(pm + 3 * i, pq + 4 * i, ps + 3 * i, cam, k, vm + 2 * i, vc + 3 * i, vd[i],
                           gm + 3 * i, gq + 4 * i, gs + 3 * i);
  return {g_means, g_quats, g_scales};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &forward, "rasterize 2D Gaussians (forward)");
  m.def("backward", &backward, "rasterize 2D Gaussians (backward)");
  m.def("project_forward", &project_fwd, "EWA projection (forward)");
  m.def("project_backward", &project_bwd, "EWA projection (backward)");
}
