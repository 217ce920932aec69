"""Builds torchrot's C++ extension (torchrot._C) against the installed torch.

The CPU kernel is compiled once per instruction set, each object with its own
flags and CPU_CAPABILITY (so ATen's Vectorized<T> and every inline function of
the kernel headers get a distinct, ISA-specific definition); the dispatch in
csrc/cpu/dispatch.cpp picks one at run time. The baseline objects are linked
first: should any inline function outside the kernel's namespaces be emitted
by several objects, the linker keeps the baseline copy, never an AVX one.

The objects depend on the target, which the compiler itself reports (so a
cross compiler, CC=aarch64-linux-gnu-gcc, is answered for its target): on
x86-64 all four (scalar, default, avx2, avx512); anywhere else (aarch64 Linux,
Apple silicon, ...) scalar and default, where default is ATen's Vectorized<T>
for that target (NEON on aarch64). csrc/cpu/kernel_table.h tests the same
macros to reference the AVX objects only on x86-64. OpenMP (-fopenmp) is used
where the compiler accepts it (not Apple clang: at::parallel_for is then
serial). On x86-64 with GCC or clang the flags are those of the fixed list
(and GCC_FLAGS where the compiler is GCC).
"""
import glob
import os
import platform
import subprocess
import tempfile

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

BASELINE_KERNELS = [  # (source, flags): every target
    ("csrc/cpu/kernel_scalar.cpp", ["-DCPU_CAPABILITY=SCALAR"]),
    ("csrc/cpu/kernel_default.cpp", ["-DCPU_CAPABILITY=DEFAULT", "-DCPU_CAPABILITY_DEFAULT"]),
]
# GCC only: ATen's generic Vectorized (the default object) is arrays and
# loops, so every +, * is a call unless inlined, and the fits are single large
# functions: GCC stopped inlining them at its large-function-growth limit
# (100%), which left ~140 calls per one-step block and made that kernel 30-60%
# slower (measured on x86-64, after an unrelated change moved the limit).
GCC_FLAGS = {"csrc/cpu/kernel_default.cpp": ["--param=large-function-growth=100000"]}
X86_64_KERNELS = [  # x86-64 targets only
    ("csrc/cpu/kernel_avx2.cpp", ["-DCPU_CAPABILITY=AVX2", "-DCPU_CAPABILITY_AVX2", "-mavx2", "-mfma", "-mf16c"]),
    (
        "csrc/cpu/kernel_avx512.cpp",
        ["-DCPU_CAPABILITY=AVX512", "-DCPU_CAPABILITY_AVX512", "-mavx512f", "-mavx512bw", "-mavx512vl",
         "-mavx512dq", "-mfma", "-mf16c"],
    ),
]

# What the compiler's preprocessor says about its target (the test of
# TORCHROT_X86_64_KERNELS in csrc/cpu/kernel_table.h, and OpenMP).
TARGET_PROBE = """
#if defined(__x86_64__) || defined(_M_X64)
torchrot_target_x86_64
#endif
#ifdef _OPENMP
torchrot_openmp
#endif
#if defined(__GNUC__) && !defined(__clang__)
torchrot_gcc
#endif
"""


def probe_target(compiler_so, flags):
    """(x86_64, openmp, gcc) for this compiler command and flags, or None if the
    compiler cannot be asked (then the caller falls back to the host)."""
    if not compiler_so:
        return None
    with tempfile.TemporaryDirectory() as tmp:
        source = os.path.join(tmp, "probe.cpp")
        with open(source, "w") as f:
            f.write(TARGET_PROBE)
        for extra in (["-fopenmp"], []):  # -fopenmp: rejected by Apple clang
            try:
                result = subprocess.run([*compiler_so, *flags, *extra, "-E", source], capture_output=True, text=True)
            except OSError:
                return None
            if result.returncode == 0:
                out = result.stdout
                return "torchrot_target_x86_64" in out, "torchrot_openmp" in out, "torchrot_gcc" in out
    return None


class BuildWithIsaKernels(BuildExtension):
    """Compiles each ISA kernel of the target with its own flags and links the objects in."""

    def build_extension(self, ext):
        args = ext.extra_compile_args
        cxx = args["cxx"] if isinstance(args, dict) else args  # incl. torch's ABI flags
        probe = probe_target(getattr(self.compiler, "compiler_so", None), [f for f in cxx if f != "-fopenmp"])
        if probe is None:
            x86_64, openmp, gcc = platform.machine().lower() in ("x86_64", "amd64"), False, False
            print(f"torchrot: could not run the compiler's preprocessor; building for {platform.machine()}, no OpenMP")
        else:
            x86_64, openmp, gcc = probe
        if not openmp:
            for flags in (cxx, ext.extra_link_args):
                while "-fopenmp" in flags:
                    flags.remove("-fopenmp")
        kernels = BASELINE_KERNELS + (X86_64_KERNELS if x86_64 else [])
        print(f"torchrot: kernel objects {', '.join(os.path.basename(s) for s, _ in kernels)}; "
              f"OpenMP {'on' if openmp else 'off (at::parallel_for is serial)'}")
        base = list(cxx)
        objects = []
        for source, flags in kernels:
            objects += self.compiler.compile(
                [source],
                output_dir=self.build_temp,
                include_dirs=ext.include_dirs,
                extra_postargs=base + flags + (GCC_FLAGS.get(source, []) if gcc else []),
                depends=ext.depends,
            )
        ext.extra_objects = objects + list(ext.extra_objects or [])
        super().build_extension(ext)


setup(
    ext_modules=[
        CppExtension(
            name="torchrot._C",
            sources=["csrc/module.cpp", "csrc/ops.cpp", "csrc/autograd.cpp", "csrc/cpu/dispatch.cpp"],
            depends=sorted(glob.glob("csrc/**/*.h", recursive=True)),
            extra_compile_args=COMMON_FLAGS + SANITIZE_FLAGS,
            extra_link_args=["-fopenmp"] + SANITIZE_FLAGS,
        )
    ],
    cmdclass={"build_ext": BuildWithIsaKernels},
)
