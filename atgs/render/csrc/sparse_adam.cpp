// Row-sparse Adam on the CPU: one pass over the touched rows of a table, fused.
//
// It computes what atgs/train/optim.py's torch version computes (the reference the tests
// compare against): non-finite gradient entries read as 0, the gradient is scaled to norm
// ``clip`` when above it, and each row gets an Adam update with its own step count. The torch
// version runs a dozen whole-tensor ops per table (index_select of the moments and steps,
// bias corrections, index_copy back), each a pass over memory and a dispatch; here every row is
// read and written once, which matters for the hash tables (hundreds of thousands of short rows
// per step).
#include <ATen/core/Tensor.h>
#include <torch/csrc/utils/pybind.h>

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr int64_t kParallelMin = 4096;  // fewer values: a fork-join costs more than it saves

inline float finite_or_zero(float g) { return std::isfinite(g) ? g : 0.0f; }

// Sum of squares of the gradient's finite entries, in double.
double squared_norm(const float* g, int64_t n, int nt) {
  double acc = 0.0;
#pragma omp parallel for schedule(static) reduction(+ : acc) num_threads(nt) if (n > kParallelMin)
  for (int64_t i = 0; i < n; ++i) {
    const double v = finite_or_zero(g[i]);
    acc += v * v;
  }
  return acc;
}

// table, exp_avg, exp_avg_sq: (R, ...) float32 contiguous; steps: (R,) int64; rows: (U,) int64
// unique; grad: (U, ...) float32; lr_rows: (U,) float32 or empty (then ``lr`` for every row).
void step(at::Tensor table, at::Tensor exp_avg, at::Tensor exp_avg_sq, at::Tensor steps, at::Tensor rows,
          at::Tensor grad, at::Tensor lr_rows, double lr, double beta1, double beta2, double eps, double clip,
          int64_t threads) {
  TORCH_CHECK(table.is_contiguous() && exp_avg.is_contiguous() && exp_avg_sq.is_contiguous() &&
                  steps.is_contiguous() && rows.is_contiguous() && grad.is_contiguous() && lr_rows.is_contiguous(),
              "sparse_adam: tensors must be contiguous");
  TORCH_CHECK(table.scalar_type() == at::kFloat && grad.scalar_type() == at::kFloat &&
                  exp_avg.scalar_type() == at::kFloat && exp_avg_sq.scalar_type() == at::kFloat,
              "sparse_adam: float32 tables and gradients only");
  TORCH_CHECK(steps.scalar_type() == at::kLong && rows.scalar_type() == at::kLong, "sparse_adam: int64 rows");
  const int64_t num_rows = rows.numel();
  if (num_rows == 0) return;
  const int64_t width = table.size(0) ? table.numel() / table.size(0) : 0;
  TORCH_CHECK(grad.numel() == num_rows * width, "sparse_adam: grad must have one row per entry of rows");
  const bool per_row_lr = lr_rows.numel() > 0;
  TORCH_CHECK(!per_row_lr || (lr_rows.numel() == num_rows && lr_rows.scalar_type() == at::kFloat),
              "sparse_adam: lr_rows must be float32, one per row");
  const int nt = int(std::max<int64_t>(1, threads));

  const float* g = grad.data_ptr<float>();
  float scale = 1.0f;
  if (clip > 0.0) {
    // as the torch version: the norm in float32, the ratio in double, applied in float32
    const double norm = double(float(std::sqrt(squared_norm(g, grad.numel(), nt))));
    if (norm > clip) scale = float(clip / norm);
  }
  float* p = table.data_ptr<float>();
  float* m = exp_avg.data_ptr<float>();
  float* v = exp_avg_sq.data_ptr<float>();
  int64_t* n = steps.data_ptr<int64_t>();
  const int64_t* r = rows.data_ptr<int64_t>();
  const float* lrs = per_row_lr ? lr_rows.data_ptr<float>() : nullptr;
  const float b1 = float(beta1), b2 = float(beta2), one_b1 = float(1.0 - beta1), one_b2 = float(1.0 - beta2);
  const float fe = float(eps), flr = float(lr);
  const int64_t total = table.size(0);
  int64_t max_count = 0;
  for (int64_t i = 0; i < num_rows; ++i) {  // checked here: an exception must not leave a parallel loop
    TORCH_CHECK(r[i] >= 0 && r[i] < total, "sparse_adam: row ", r[i], " out of range for a table of ", total);
    max_count = std::max(max_count, n[r[i]] + 1);
  }
  // Bias corrections 1 - beta^n, per step count n; beta^n as exp(n log beta) (the same in
  // float32, cheaper than pow). Tabulated when there are fewer counts than rows (the hash
  // tables: ~10^5 rows a step, at most as many counts as steps).
  const double log_b1 = std::log(beta1), log_b2 = std::log(beta2);
  auto correction = [&](int64_t count, float& bc1, float& bc2) {
    bc1 = float(1.0 - std::exp(double(count) * log_b1));
    bc2 = float(1.0 - std::exp(double(count) * log_b2));
  };
  std::vector<float> table1, table2;
  const bool tabulate = max_count < num_rows;
  if (tabulate) {
    table1.resize(max_count + 1);
    table2.resize(max_count + 1);
    for (int64_t k = 1; k <= max_count; ++k) correction(k, table1[k], table2[k]);
  }

#pragma omp parallel for schedule(static) num_threads(nt) if (num_rows * width > kParallelMin)
  for (int64_t i = 0; i < num_rows; ++i) {
    const int64_t row = r[i];
    const int64_t count = n[row] + 1;
    n[row] = count;
    float bc1, bc2;
    if (tabulate) {
      bc1 = table1[count];
      bc2 = table2[count];
    } else {
      correction(count, bc1, bc2);
    }
    const float rate = lrs ? lrs[i] : flr;
    const float* gi = g + i * width;
    float* pi = p + row * width;
    float* mi = m + row * width;
    float* vi = v + row * width;
    for (int64_t j = 0; j < width; ++j) {
      const float gj = finite_or_zero(gi[j]) * scale;
      const float mj = mi[j] * b1 + one_b1 * gj;
      const float vj = vi[j] * b2 + one_b2 * gj * gj;
      mi[j] = mj;
      vi[j] = vj;
      pi[j] -= rate * ((mj / bc1) / (std::sqrt(vj / bc2) + fe));
    }
  }
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("step", &step, "row-sparse Adam step of one table (in place)");
}
