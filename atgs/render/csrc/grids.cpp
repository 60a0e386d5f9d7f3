// Feature-grid encodings of the ATGS model on the CPU: the 4D multi-resolution hash grid F_T
// (quadrilinear) and the dense 3D grid F_s (trilinear), forward and backward.
//
// They compute exactly what atgs/model/grids.py computes with torch ops (the reference the tests
// compare against): the same float32 cell/weight arithmetic, the same dense indexing or
// Instant-NGP hash, and the same table rows. The torch version builds (N, L, 16) index and
// weight tensors and scatters with index_put; here each point's corners are computed, used and
// forgotten, which makes the training decode several times faster.
//
// ``touched`` marks the table rows a query reads: atgs/model/grids.py turns them into the small
// leaf tensor that autograd and the sparse optimizer see. Backward scatters either into a
// table-sized gradient (``remap`` empty; the caller reads the touched rows out of it: best for
// the large hash tables with few features, where a remap read per corner misses the cache) or,
// through ``remap`` (table row -> leaf row), straight into the leaf's gradient (best for the
// dense grid: few rows, many features).
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/sum.h>
#include <ATen/ops/zeros.h>
#include <torch/csrc/utils/pybind.h>

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr uint64_t kPrimes[4] = {1ull, 2654435761ull, 805459861ull, 3674653429ull};
constexpr int64_t kParallelMin = 2048;  // fewer points: a fork-join costs more than it saves

// One level of a grid: vertices (res + 1) per spatial axis and (time_res + 1) in time.
struct Level {
  int64_t res, time_res;
  bool dense;
  int64_t row0;  // first table row of this level (grid and level offset)
};

// Cell and weights along one axis, in float32 as interp_indices: pos = clamp(x) * r,
// base = clamp(min(floor(pos), r - 1), 0), frac = pos - base. NaN reads as 0 (never an
// out-of-range row).
inline void axis(float x, int64_t r, int64_t& base, float& frac) {
  const float rf = float(r);
  const float pos = (x > 0.0f ? (x < 1.0f ? x : 1.0f) : 0.0f) * rf;
  const float b = std::max(std::min(std::floor(pos), rf - 1.0f), 0.0f);
  base = int64_t(b);
  frac = pos - b;
}

// Calls f(corner, row, weight) for the 2^D corners of point p (D = 3 or 4; the 4th coordinate
// is the time t). Corner c has offset bit d = (c >> d) & 1, as _corner_offsets.
template <int D, typename F>
inline void for_corners(const float* p, float t, const Level& lv, int64_t table_size, F&& f) {
  int64_t base[4];
  float frac[4];
  for (int d = 0; d < 3; ++d) axis(p[d], lv.res, base[d], frac[d]);
  if (D == 4) axis(t, lv.time_res, base[3], frac[3]);
  const int64_t r1 = lv.res + 1;
  for (int c = 0; c < (1 << D); ++c) {
    int64_t v[4];
    float w = 1.0f;
    for (int d = 0; d < D; ++d) {
      const int64_t o = (c >> d) & 1;
      v[d] = base[d] + o;
      w *= o ? frac[d] : 1.0f - frac[d];
    }
    int64_t slot;
    if (lv.dense) {
      slot = v[0] + r1 * (v[1] + r1 * v[2]);
      if (D == 4) slot += r1 * r1 * r1 * v[3];
    } else {
      uint64_t h = uint64_t(v[0]) * kPrimes[0];
      for (int d = 1; d < D; ++d) h ^= uint64_t(v[d]) * kPrimes[d];
      slot = int64_t(h & uint64_t(table_size - 1));
    }
    f(c, lv.row0 + slot, w);
  }
}

std::vector<Level> make_levels(const std::vector<int64_t>& res, const std::vector<int64_t>& time_res,
                               const std::vector<int64_t>& dense, int64_t grid, int64_t table_size) {
  TORCH_CHECK(res.size() == time_res.size() && res.size() == dense.size(), "level lists differ in length");
  const int64_t L = int64_t(res.size());
  std::vector<Level> levels;
  for (int64_t l = 0; l < L; ++l)
    levels.push_back({res[l], time_res[l], dense[l] != 0, (grid * L + l) * table_size});
  return levels;
}

void check_points(const at::Tensor& x) {
  TORCH_CHECK(x.device().is_cpu() && x.scalar_type() == at::kFloat && x.is_contiguous() && x.dim() == 2 &&
                  x.size(1) == 3,
              "points must be a contiguous (N, 3) float32 CPU tensor");
}

template <int D>
at::Tensor touched(const at::Tensor& x, double t, const std::vector<Level>& levels, int64_t table_size,
                   int64_t rows, int64_t threads) {
  check_points(x);
  at::Tensor mask = at::zeros({rows}, x.options().dtype(at::kBool));
  bool* m = mask.data_ptr<bool>();
  const float* px = x.data_ptr<float>();
  const int64_t n = x.size(0);
  // Benign race: every writer stores the same value.
#pragma omp parallel for schedule(static) num_threads(int(std::max<int64_t>(1, threads))) if (n > kParallelMin)
  for (int64_t i = 0; i < n; ++i)
    for (const Level& lv : levels)
      for_corners<D>(px + 3 * i, float(t), lv, table_size, [&](int, int64_t row, float) { m[row] = true; });
  return mask;
}

template <int D>
at::Tensor forward(const at::Tensor& x, double t, const std::vector<Level>& levels, int64_t table_size,
                   const at::Tensor& values, int64_t threads) {
  check_points(x);
  TORCH_CHECK(values.scalar_type() == at::kFloat && values.is_contiguous() && values.dim() == 2,
              "values must be a contiguous 2D float32 tensor");
  const int64_t n = x.size(0), F = values.size(1), L = int64_t(levels.size());
  at::Tensor out = at::empty({n, L * F}, x.options());
  const float* px = x.data_ptr<float>();
  const float* pv = values.data_ptr<float>();
  float* po = out.data_ptr<float>();
#pragma omp parallel for schedule(static) num_threads(int(std::max<int64_t>(1, threads))) if (n > kParallelMin)
  for (int64_t i = 0; i < n; ++i) {
    for (int64_t l = 0; l < L; ++l) {
      float* o = po + (i * L + l) * F;
      for (int64_t f = 0; f < F; ++f) o[f] = 0.0f;
      for_corners<D>(px + 3 * i, float(t), levels[l], table_size, [&](int, int64_t row, float w) {
        const float* v = pv + row * F;
        for (int64_t f = 0; f < F; ++f) o[f] += w * v[f];
      });
    }
  }
  return out;
}

// Each thread accumulates into its own zeroed copy of the gradient when the copies are small
// (no atomics: a float atomic add is a compare-and-swap loop), else all add atomically.
constexpr int64_t kPrivateMaxFloats = int64_t(1) << 22;

template <int D>
at::Tensor backward(const at::Tensor& x, double t, const std::vector<Level>& levels, int64_t table_size,
                    const at::Tensor& grad_out, int64_t value_rows, const at::Tensor& remap, int64_t threads) {
  check_points(x);
  const int64_t n = x.size(0), L = int64_t(levels.size());
  TORCH_CHECK(grad_out.scalar_type() == at::kFloat && grad_out.is_contiguous() && grad_out.size(0) == n &&
                  grad_out.size(1) % L == 0,
              "grad_out must be a contiguous (N, L*F) float32 tensor");
  const int64_t F = grad_out.size(1) / L;
  const int nt = int(std::max<int64_t>(1, n > kParallelMin ? threads : 1));
  const bool priv = nt > 1 && nt * value_rows * F <= kPrivateMaxFloats;
  at::Tensor grad = at::zeros({priv ? nt : 1, value_rows, F}, x.options());
  const float* px = x.data_ptr<float>();
  const float* pg = grad_out.data_ptr<float>();
  const int64_t* pr = remap.numel() ? remap.data_ptr<int64_t>() : nullptr;
  float* out = grad.data_ptr<float>();
#pragma omp parallel num_threads(nt)
  {
    float* mine = priv ? out + int64_t(omp_get_thread_num()) * value_rows * F : out;
#pragma omp for schedule(static)
    for (int64_t i = 0; i < n; ++i) {
      for (int64_t l = 0; l < L; ++l) {
        const float* g = pg + (i * L + l) * F;
        for_corners<D>(px + 3 * i, float(t), levels[l], table_size, [&](int, int64_t row, float w) {
          float* dst = mine + (pr ? pr[row] : row) * F;
          for (int64_t f = 0; f < F; ++f) {
            if (priv || nt == 1) {
              dst[f] += w * g[f];
            } else {
#pragma omp atomic
              dst[f] += w * g[f];
            }
          }
        });
      }
    }
  }
  return priv ? grad.sum(0) : grad[0];
}

// ---- bindings: hash grid (4D, L levels of grid `grid`) and dense grid (3D, one level) ----

at::Tensor hash_touched(at::Tensor x, double t, int64_t grid, std::vector<int64_t> res, std::vector<int64_t> time_res,
                        std::vector<int64_t> dense, int64_t table_size, int64_t rows, int64_t threads) {
  return touched<4>(x, t, make_levels(res, time_res, dense, grid, table_size), table_size, rows, threads);
}

at::Tensor hash_forward(at::Tensor x, double t, int64_t grid, std::vector<int64_t> res, std::vector<int64_t> time_res,
                        std::vector<int64_t> dense, int64_t table_size, at::Tensor values, int64_t threads) {
  return forward<4>(x, t, make_levels(res, time_res, dense, grid, table_size), table_size, values, threads);
}

at::Tensor hash_backward(at::Tensor x, double t, int64_t grid, std::vector<int64_t> res,
                         std::vector<int64_t> time_res, std::vector<int64_t> dense, int64_t table_size,
                         at::Tensor grad_out, int64_t value_rows, at::Tensor remap, int64_t threads) {
  return backward<4>(x, t, make_levels(res, time_res, dense, grid, table_size), table_size, grad_out.contiguous(),
                     value_rows, remap, threads);
}

// The dense grid has res vertices per axis: a level of res - 1 cells, indexed densely.
std::vector<Level> dense_level(int64_t res) { return {{res - 1, 1, true, 0}}; }

at::Tensor dense_touched(at::Tensor x, int64_t res, int64_t threads) {
  return touched<3>(x, 0.0, dense_level(res), 0, res * res * res, threads);
}

at::Tensor dense_forward(at::Tensor x, int64_t res, at::Tensor values, int64_t threads) {
  return forward<3>(x, 0.0, dense_level(res), 0, values, threads);
}

at::Tensor dense_backward(at::Tensor x, int64_t res, at::Tensor grad_out, int64_t value_rows, at::Tensor remap,
                          int64_t threads) {
  return backward<3>(x, 0.0, dense_level(res), 0, grad_out.contiguous(), value_rows, remap, threads);
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("hash_touched", &hash_touched, "table rows a 4D hash-grid query reads");
  m.def("hash_forward", &hash_forward, "4D hash-grid encoding (forward)");
  m.def("hash_backward", &hash_backward, "4D hash-grid encoding (backward)");
  m.def("dense_touched", &dense_touched, "table rows a dense 3D grid query reads");
  m.def("dense_forward", &dense_forward, "dense 3D grid trilinear lookup (forward)");
  m.def("dense_backward", &dense_backward, "dense 3D grid trilinear lookup (backward)");
}
