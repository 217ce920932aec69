// Batched CPU driver: walks the (N, 3, 3) batch in parallel and fits each
// matrix with kernel::fit_rotation_one. Matrices are independent, so the result
// does not depend on the number of threads.
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>

#include <atomic>

#include "../fit_rotation.h"
#include "../kernel/fit_rotation_impl.h"

namespace torchrot {
namespace {

// Enough matrices per task that scheduling costs little next to the work.
constexpr int64_t kGrainSize = 1024;

// Element (i, r, c) of an (N, 3, 3) tensor with arbitrary strides.
template <typename T>
struct StridedMatrices {
  T* data;
  int64_t batch_stride, row_stride, col_stride;

  explicit StridedMatrices(const at::Tensor& t)
      : data(t.data_ptr<std::remove_const_t<T>>()),
        batch_stride(t.stride(0)),
        row_stride(t.stride(1)),
        col_stride(t.stride(2)) {}

  kernel::Mat3<std::remove_const_t<T>> load(int64_t i) const {
    kernel::Mat3<std::remove_const_t<T>> A;
    const T* base = data + i * batch_stride;
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) A(r, c) = base[r * row_stride + c * col_stride];
    return A;
  }

  void store(int64_t i, const kernel::Mat3<T>& A) const {
    T* base = data + i * batch_stride;
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) base[r * row_stride + c * col_stride] = A(r, c);
  }
};

template <typename T>
int64_t fit_batch(const at::Tensor& M, const at::Tensor* init, const at::Tensor& out,
                  const FitOptions& options, int32_t* iterations, uint8_t* status) {
  const StridedMatrices<const T> m_view(M);
  const StridedMatrices<T> out_view(out);
  const bool has_init = init != nullptr;
  const StridedMatrices<const T> init_view(has_init ? *init : M);
  std::atomic<int64_t> bad_inits{0};
  at::parallel_for(0, M.size(0), kGrainSize, [&](int64_t begin, int64_t end) {
    int64_t local_bad = 0;
    for (int64_t i = begin; i < end; ++i) {
      // Both inputs are read into registers before `out` is written, so out
      // may alias M or init.
      const kernel::Mat3<T> A = m_view.load(i);
      kernel::Mat3<T> R0;
      if (has_init) R0 = init_view.load(i);
      kernel::Mat3<T> R;
      const kernel::FitResult res =
          kernel::fit_rotation_one(A, has_init ? &R0 : nullptr, options, R);
      out_view.store(i, R);
      if (iterations != nullptr) iterations[i] = res.iterations;
      if (status != nullptr) status[i] = static_cast<uint8_t>(res.status);
      local_bad += res.status == FitStatus::kBadInit;
    }
    bad_inits += local_bad;
  });
  return bad_inits.load();
}

}  // namespace

int64_t fit_rotation_cpu(const at::Tensor& M, const at::Tensor* init,
                         const at::Tensor& out, const FitOptions& options,
                         const at::Tensor* iterations, const at::Tensor* status) {
  int64_t bad = 0;
  AT_DISPATCH_FLOATING_TYPES(M.scalar_type(), "torchrot_fit_rotation_cpu", [&] {
    bad = fit_batch<scalar_t>(
        M, init, out, options,
        iterations != nullptr ? iterations->data_ptr<int32_t>() : nullptr,
        status != nullptr ? status->data_ptr<uint8_t>() : nullptr);
  });
  return bad;
}

}  // namespace torchrot
