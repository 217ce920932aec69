// Run-time choice of the kernel object (instruction set), and the call into it.
//
// The hardware level comes from ATen (at::get_cpu_capability(), which reads
// the CPU's features and honours ATEN_CPU_CAPABILITY). The environment
// variable TORCHROT_CPU_CAPABILITY = scalar | default | avx2 | avx512 can only
// lower it: a request above what the CPU supports is capped, so no setting
// can make torchrot execute instructions the CPU lacks. It is read once, when
// torchrot is imported (torchrot/__init__.py asks for the kernel name, which
// raises for a bad value); a thread can force another kernel for its own calls
// with set_thread_cpu_kernel (torchrot.testing.cpu_kernel), which never
// affects other threads.
//
// The names are one ordered scale on every architecture. The avx2 and avx512
// objects exist on x86-64 only (TORCHROT_X86_64_KERNELS, kernel_table.h); on
// any other target (aarch64, ...) the hardware level is "default", the
// portable object, in which ATen's Vectorized<T> is NEON on aarch64 (4 float,
// 2 double lanes; whatever at::get_cpu_capability() says, SVE256 included),
// so there a request for avx2 or avx512 is capped to "default" like any
// request above the hardware, and cpu_kernel() names "scalar" or "default".
#include <ATen/Dispatch.h>
#include <ATen/Version.h>
#include <c10/util/Exception.h>

#include <algorithm>
#include <cstdlib>
#include <cstring>
#include <string>

#include "../fit_rotation.h"
#include "../messages.h"
#include "kernel_table.h"

namespace torchrot {
namespace {

// The levels of kCpuKernelNames, in its order.
enum class Isa : int { kScalar = 0, kDefault = 1, kAvx2 = 2, kAvx512 = 3 };

constexpr const char* kEnvironmentVariable = "TORCHROT_CPU_CAPABILITY";

Isa hardware_isa() {
  static const Isa isa = [] {
#if TORCHROT_X86_64_KERNELS
    const std::string cap = at::get_cpu_capability();
    if (cap == "AVX512") return Isa::kAvx512;
    if (cap == "AVX2") return Isa::kAvx2;
#endif
    return Isa::kDefault;
  }();
  return isa;
}

// The level named `text` (case-insensitive), capped at the hardware's.
Isa parse_isa(const char* text, const char* what) {
  for (int i = 0; i < 4; ++i) {
    if (strcasecmp(text, kCpuKernelNames[i]) == 0) return std::min(static_cast<Isa>(i), hardware_isa());
  }
  TORCH_CHECK_VALUE(false, messages::format(messages::kCpuKernel, {{"what", what}, {"value", text}}));
}

// The process-wide level: TORCHROT_CPU_CAPABILITY as it was at the first call
// (thread-safe static initialisation; a bad value raises and is read again
// next time, so the import that makes the first call fails with the message).
Isa process_isa() {
  static const Isa isa = [] {
    const char* requested = std::getenv(kEnvironmentVariable);
    if (requested == nullptr || requested[0] == '\0') return hardware_isa();
    return parse_isa(requested, kEnvironmentVariable);
  }();
  return isa;
}

// A level forced by the calling thread (-1: none).
thread_local int forced_isa = -1;

Isa selected_isa() { return forced_isa >= 0 ? static_cast<Isa>(forced_isa) : process_isa(); }

const cpu::KernelTable& kernels(Isa isa) {
  switch (isa) {
#if TORCHROT_X86_64_KERNELS
    case Isa::kAvx512:
      return cpu::avx512_kernels();
    case Isa::kAvx2:
      return cpu::avx2_kernels();
#else
    case Isa::kAvx512:
    case Isa::kAvx2:  // unreachable: capped at hardware_isa(), kDefault here
#endif
    case Isa::kDefault:
      return cpu::default_kernels();
    case Isa::kScalar:
      break;
  }
  return cpu::scalar_kernels();
}

template <typename T>
void fill_view(const MatrixBatch& batch, const T*& data, Layout& layout) {
  data = static_cast<const T*>(batch.data);
  layout = batch.layout;
}

WarmStartCount run_kernel(const cpu::KernelTable& table, const cpu::WarmStartArgs<float>& args) {
  return table.bad_warm_starts_float(args);
}

WarmStartCount run_kernel(const cpu::KernelTable& table, const cpu::WarmStartArgs<double>& args) {
  return table.bad_warm_starts_double(args);
}

int64_t run_kernel(const cpu::KernelTable& table, const cpu::BatchArgs<float>& args) { return table.fit_float(args); }

int64_t run_kernel(const cpu::KernelTable& table, const cpu::BatchArgs<double>& args) { return table.fit_double(args); }

void run_kernel(const cpu::KernelTable& table, const cpu::TangentArgs<float>& args) { table.tangent_float(args); }

void run_kernel(const cpu::KernelTable& table, const cpu::TangentArgs<double>& args) { table.tangent_double(args); }

}  // namespace

std::string cpu_kernel_name() { return kernels(selected_isa()).name; }

bool cpu_kernel_fuses_multiply_add() { return kernels(selected_isa()).fused_multiply_add; }

std::string set_thread_cpu_kernel(const std::string& name) {
  const std::string previous = forced_isa >= 0 ? kCpuKernelNames[forced_isa] : "";
  if (name.empty()) {
    forced_isa = -1;
  } else {
    forced_isa = static_cast<int>(parse_isa(name.c_str(), "torchrot.testing.cpu_kernel: name"));
  }
  return previous;
}

WarmStartCount count_bad_warm_starts_cpu(at::ScalarType dtype, int64_t n, const MatrixBatch& init) {
  const cpu::KernelTable& table = kernels(selected_isa());
  WarmStartCount bad;
  AT_DISPATCH_FLOATING_TYPES(dtype, "torchrot_count_bad_warm_starts_cpu", [&] {
    cpu::WarmStartArgs<scalar_t> args{};
    fill_view(init, args.init, args.layout);
    args.n = n;
    bad = run_kernel(table, args);
  });
  return bad;
}

int64_t fit_rotation_cpu(at::ScalarType dtype, int64_t n, const MatrixBatch& M, const MatrixBatch* init,
                         const MatrixBatch& out, const FitOptions& options, int32_t* iterations, uint8_t* status) {
  const cpu::KernelTable& table = kernels(selected_isa());
  int64_t bad_inits = 0;
  AT_DISPATCH_FLOATING_TYPES(dtype, "torchrot_fit_rotation_cpu", [&] {
    cpu::BatchArgs<scalar_t> args{};
    fill_view(M, args.M, args.m_layout);
    if (init != nullptr) fill_view(*init, args.init, args.init_layout);
    const scalar_t* out_data = nullptr;
    fill_view(out, out_data, args.out_layout);
    args.out = const_cast<scalar_t*>(out_data);
    args.n = n;
    args.options = options;
    args.iterations = iterations;
    args.status = status;
    bad_inits = run_kernel(table, args);
  });
  return bad_inits;
}

void rotation_tangent_cpu(at::ScalarType dtype, int64_t n, const MatrixBatch& X, const MatrixBatch& R,
                          const MatrixBatch& M, const MatrixBatch& out, double damping) {
  const cpu::KernelTable& table = kernels(selected_isa());
  AT_DISPATCH_FLOATING_TYPES(dtype, "torchrot_rotation_tangent_cpu", [&] {
    cpu::TangentArgs<scalar_t> args{};
    fill_view(X, args.X, args.x_layout);
    fill_view(R, args.R, args.r_layout);
    fill_view(M, args.M, args.m_layout);
    const scalar_t* out_data = nullptr;
    fill_view(out, out_data, args.out_layout);
    args.out = const_cast<scalar_t*>(out_data);
    args.n = n;
    args.damping = static_cast<scalar_t>(damping);
    run_kernel(table, args);
  });
}

}  // namespace torchrot
