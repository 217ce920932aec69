"""Builds torchrot's C++ extension (torchrot._C) against the installed torch.

The CPU kernel is compiled once per instruction set, each object with its own
flags and CPU_CAPABILITY (so ATen's Vectorized<T> and every inline function of
the kernel headers get a distinct, ISA-specific definition); the dispatch in
csrc/cpu/dispatch.cpp picks one at run time. The baseline objects are linked
first: should any inline function outside the kernel's namespaces be emitted
by several objects, the linker keeps the baseline copy, never an AVX one.
"""
import glob
import os

from setuptools import setup
from torch.utils.cpp_extension import BuildExtension, CppExtension

# -fopenmp: at::parallel_for is serial without it.
COMMON_FLAGS = ["-O3", "-std=c++17", "-fopenmp", "-fvisibility=hidden", "-ffp-contract=off"]

# Sanitizer build (.ci/sanitize): TORCHROT_SANITIZE=address,undefined compiles
# and links every object with -fsanitize=address,undefined (any -fsanitize
# list), debug info and no recovery, so the first error aborts; at -O1 (the
# sanitizers' recommendation: instrumented -O3 AVX-512 objects took many
# minutes each to compile). Unset or empty: the normal build, unchanged.
SANITIZE = os.environ.get("TORCHROT_SANITIZE", "").strip()
SANITIZE_FLAGS = (
    [f"-fsanitize={SANITIZE}", "-fno-sanitize-recover=all", "-fno-omit-frame-pointer", "-g", "-O1"]
    if SANITIZE else []
)

ISA_KERNELS = [  # (source, flags), baseline first
    ("csrc/cpu/kernel_scalar.cpp", ["-DCPU_CAPABILITY=SCALAR"]),
    ("csrc/cpu/kernel_default.cpp", ["-DCPU_CAPABILITY=DEFAULT", "-DCPU_CAPABILITY_DEFAULT"]),
    ("csrc/cpu/kernel_avx2.cpp", ["-DCPU_CAPABILITY=AVX2", "-DCPU_CAPABILITY_AVX2", "-mavx2", "-mfma", "-mf16c"]),
    (
        "csrc/cpu/kernel_avx512.cpp",
        ["-DCPU_CAPABILITY=AVX512", "-DCPU_CAPABILITY_AVX512", "-mavx512f", "-mavx512bw", "-mavx512vl",
         "-mavx512dq", "-mfma", "-mf16c"],
    ),
]


class BuildWithIsaKernels(BuildExtension):
    """Compiles each ISA kernel with its own flags and links the objects in."""

    def build_extension(self, ext):
        args = ext.extra_compile_args
        base = list(args["cxx"] if isinstance(args, dict) else args)  # incl. torch's ABI flags
        objects = []
        for source, flags in ISA_KERNELS:
            objects += self.compiler.compile(
                [source],
                output_dir=self.build_temp,
                include_dirs=ext.include_dirs,
                extra_postargs=base + flags,
                depends=ext.depends,
            )
        ext.extra_objects = objects + list(ext.extra_objects or [])
        super().build_extension(ext)


setup(
    ext_modules=[
        CppExtension(
            name="torchrot._C",
            sources=["csrc/module.cpp", "csrc/ops.cpp", "csrc/cpu/dispatch.cpp"],
            depends=sorted(glob.glob("csrc/**/*.h", recursive=True)),
            extra_compile_args=COMMON_FLAGS + SANITIZE_FLAGS,
            extra_link_args=["-fopenmp"] + SANITIZE_FLAGS,
        )
    ],
    cmdclass={"build_ext": BuildWithIsaKernels},
)
