// The operators of torch.ops.torchrot (TORCH_LIBRARY). Their kernels:
// fit_rotation_cpu.cpp (CPU), ../autograd.cpp (Autograd, ADInplaceOrView),
// torchrot/_fake.py and torchrot/_device_kernels.py (fake kernels, other
// devices) and torchrot/_autograd.py
// (the Python Autograd twins, vmap, autocast).
#include <torch/library.h>

#include <string>

#include "schemas.h"

TORCH_LIBRARY(torchrot, m) {
  // gradient_eps only affects the derivative (see fit_rotation_backward).
  m.def("fit_rotation" TORCHROT_FIT_ROTATION_SCHEMA);
  m.def("fit_rotation_out" TORCHROT_FIT_ROTATION_OUT_SCHEMA);
  m.def("fit_rotation_info" TORCHROT_FIT_ROTATION_INFO_SCHEMA);
  // dL/dM given dL/dR = grad at R = fit_rotation(M), through the optimality
  // condition (R^T M symmetric) with Tikhonov damping gradient_eps; the same
  // map gives the forward-mode tangent dR from dM.
  m.def("fit_rotation_backward" TORCHROT_FIT_ROTATION_BACKWARD_SCHEMA);
  // Twins of fit_rotation and fit_rotation_backward that carry only their
  // Python Autograd kernels (torchrot/_autograd.py): the C++ Autograd kernel
  // of each (csrc/autograd.cpp) hands them the calls of torch.func, forward
  // mode and tracing.
  m.def("_fit_rotation_python_autograd" TORCHROT_FIT_ROTATION_SCHEMA);
  m.def("_fit_rotation_backward_python_autograd" TORCHROT_FIT_ROTATION_BACKWARD_SCHEMA);
  // Which CPU kernel object runs in the calling thread: one of kCpuKernelNames.
  m.def("cpu_kernel() -> str", [] { return torchrot::cpu_kernel_name(); });
  // Whether that kernel's results are the scalar kernel's bit for bit (it
  // rounds a * b + c once, as the scalar kernel does; see kernel/mul_add.h).
  m.def("_cpu_kernel_fuses_multiply_add() -> bool", [] { return torchrot::cpu_kernel_fuses_multiply_add(); });
  // Forces a kernel object for the calling thread ("" to stop); returns the
  // previously forced one. Use torchrot.testing.cpu_kernel(name).
  m.def("_set_cpu_kernel(str name) -> str",
        [](c10::string_view name) { return torchrot::set_thread_cpu_kernel(std::string(name)); });
}
