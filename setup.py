"""Builds torchrot's C++ extension (torchrot._C) against the installed torch."""
from setuptools import setup
from torch.utils.cpp_extension import BuildExtension, CppExtension

# -fopenmp: at::parallel_for is serial without it.
# CPU_CAPABILITY names the instruction-set namespace of the kernel headers;
# this translation unit is the portable baseline.
COMMON_FLAGS = ["-O3", "-std=c++17", "-fopenmp", "-fvisibility=hidden"]

setup(
    ext_modules=[
        CppExtension(
            name="torchrot._C",
            sources=["csrc/module.cpp", "csrc/ops.cpp", "csrc/cpu/fit_rotation_cpu.cpp"],
            extra_compile_args=COMMON_FLAGS + ["-DCPU_CAPABILITY=DEFAULT"],
            extra_link_args=["-fopenmp"],
        )
    ],
    cmdclass={"build_ext": BuildExtension},
)
