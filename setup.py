"""Builds torchrot's C++ extension (torchrot._C) against the installed torch.

torch must be installed first, and the build must see it (pip's
``--no-build-isolation``; an isolated build environment would have to install
a torch of its own, several GB, and the extension would then not match the
user's). Any torch of SUPPORTED_TORCH builds; the extension is tied to the
torch minor release it was compiled against: the package requires that
release (``torch==X.Y.*``), and ``import torchrot`` refuses, with a clear
error, a torch of another release (torchrot/_extension.py reads the version
this build writes to torchrot/_build_info.py). The C++ standard is the one
torch's own extension helpers pick for the installed torch (C++17 for torch
2.11, C++20 from 2.12; torchrot compiles as either); nothing here sets it.

The CPU kernel is compiled once per instruction set, each object with its own
flags and CPU_CAPABILITY (so ATen's Vectorized<T> and every inline function of
the kernel headers get a distinct, ISA-specific definition); the dispatch in
csrc/cpu/dispatch.cpp picks one at run time. The baseline objects are linked
first: should any inline function outside the kernel's namespaces be emitted
by several objects, the linker keeps the baseline copy, never an AVX one.

Every object (the operator sources and the kernel objects) is compiled in one
parallel build, longest first, as many at once as there are CPUs (MAX_JOBS
overrides), each finished object printed with its time (shown by ``pip -v``).

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
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor

from setuptools import setup

try:
    import torch
    from torch.utils.cpp_extension import BuildExtension, CppExtension
except ImportError:
    sys.exit(
        "torchrot compiles its C++ extension against the torch installed in this environment, and none was "
        "found. Install torch first (any release from 2.11 to 2.15), then build without isolation so that the "
        "build sees it: pip install --no-build-isolation ."
    )

# The torch releases torchrot supports and is tested against (README, "Platforms").
SUPPORTED_TORCH = ((2, 11), (2, 15))  # first and last minor release, inclusive
TORCH_RELEASE = tuple(int(part) for part in torch.__version__.split("+")[0].split(".")[:2])
if not SUPPORTED_TORCH[0] <= TORCH_RELEASE <= SUPPORTED_TORCH[1]:
    sys.exit(
        f"torchrot supports torch {'.'.join(map(str, SUPPORTED_TORCH[0]))} to "
        f"{'.'.join(map(str, SUPPORTED_TORCH[1]))}; this environment has torch {torch.__version__}"
    )

# -fopenmp: at::parallel_for is serial without it. -g0: no debug information
# (Python's own CFLAGS ask for -g, which made the kernel objects much slower to
# compile: benchmarks/lab_notes.md); TORCHROT_DEBUG_INFO=1 asks for it (-g: the
# same code, which benchmarks/instruction_profile.py attributes to source
# functions). -Wno-unknown-pragmas: torch's vector headers carry CUDA's and
# clang's pragmas, which GCC reports 78 times per build. The C++ standard is
# left to torch (see above).
DEBUG_INFO = ["-g"] if os.environ.get("TORCHROT_DEBUG_INFO", "") == "1" else ["-g0"]
COMMON_FLAGS = [*DEBUG_INFO, "-fopenmp", "-fvisibility=hidden", "-ffp-contract=off", "-Wno-unknown-pragmas"]
# The kernels are the hot code: -O3. The operator sources only check, lay out
# and dispatch (as fast at -O2 as at -O3), and compile faster at -O2
# (benchmarks/lab_notes.md).
KERNEL_OPTIMIZATION = ["-O3"]
OPERATOR_OPTIMIZATION = ["-O2"]
# x86-64's default kernel serves only CPUs without AVX2 (and its
# arrays-and-loops Vectorized is inlined by GCC_FLAGS below): at -O2 the longest
# object of the build compiles much faster (benchmarks/lab_notes.md). On other
# targets the default kernel is the main one (NEON): -O3 there.
X86_64_DEFAULT_OPTIMIZATION = ["-O2"]

# Sanitizer build (.ci/sanitize): TORCHROT_SANITIZE=address,undefined compiles
# and links every object with -fsanitize=address,undefined (any -fsanitize
# list), debug info and no recovery, so the first error aborts (these flags
# come last, so they override the optimisation and -g0); at -O1 (the
# sanitizers' recommendation: instrumented -O3 AVX-512 objects took many
# minutes each to compile). Unset or empty: the normal build, unchanged.
SANITIZE = os.environ.get("TORCHROT_SANITIZE", "").strip()
SANITIZE_FLAGS = (
    [f"-fsanitize={SANITIZE}", "-fno-sanitize-recover=all", "-fno-omit-frame-pointer", "-g", "-O1"]
    if SANITIZE else []
)

# The sources of the operators (registration, checks, autograd, the Python
# entry and the ISA dispatch), compiled with the common flags.
OPERATOR_SOURCES = sorted(glob.glob("csrc/*.cpp") + glob.glob("csrc/ops/*.cpp")) + ["csrc/cpu/dispatch.cpp"]
# The small operator sources compile as one translation unit (a unity build,
# generated in the build folder: one #include per source): each spends most of
# its time parsing torch's Tensor headers, so as one they take a fraction of the
# CPU time of an object each (benchmarks/lab_notes.md). The sources stay a file
# per job. autograd.cpp and module.cpp (torch's autograd and Python headers)
# stay objects of their own.
UNITY_SOURCES = [source for source in OPERATOR_SOURCES if source not in ("csrc/autograd.cpp", "csrc/module.cpp")]
UNITY_NAME = "operators_unity.cpp"
BASELINE_KERNELS = [  # (source, flags): every target
    ("csrc/cpu/kernel_scalar.cpp", ["-DCPU_CAPABILITY=SCALAR"]),
    ("csrc/cpu/kernel_default.cpp", ["-DCPU_CAPABILITY=DEFAULT", "-DCPU_CAPABILITY_DEFAULT"]),
]
# GCC only: ATen's generic Vectorized (the default object) is arrays and
# loops, so every +, * is a call unless inlined, and the fits are single large
# functions: GCC stopped inlining them at its large-function-growth limit
# (100%), which left calls to them in every one-step block and made that kernel
# markedly slower (on x86-64, after an unrelated change moved the limit:
# benchmarks/lab_notes.md).
#
# The AVX2 object: GCC schedules x86 code only after register allocation by
# default; -fschedule-insns schedules it before as well, and -fsched-pressure
# keeps that schedule within the 16 vector registers. A fit's block is a long
# chain of dependent vector operations, and so ordered the AVX2 fits ran
# faster (converged, cold, float64, the one-step); the AVX-512 ones (32
# registers) no faster (benchmarks/lab_notes.md).
GCC_FLAGS = {"csrc/cpu/kernel_default.cpp": ["--param=large-function-growth=100000", "-Wno-psabi"],
             "csrc/cpu/kernel_avx2.cpp": ["-fschedule-insns", "-fsched-pressure"]}
X86_64_KERNELS = [  # x86-64 targets only
    ("csrc/cpu/kernel_avx2.cpp", ["-DCPU_CAPABILITY=AVX2", "-DCPU_CAPABILITY_AVX2", "-mavx2", "-mfma", "-mf16c"]),
    (
        "csrc/cpu/kernel_avx512.cpp",
        ["-DCPU_CAPABILITY=AVX512", "-DCPU_CAPABILITY_AVX512", "-mavx512f", "-mavx512bw", "-mavx512vl",
         "-mavx512dq", "-mfma", "-mf16c",
         # GCC's own avx512fintrin.h initialises its _mm512_undefined_* vectors
         # from themselves, which -Wall reports 784 times per build (nothing of
         # torchrot's): the log would hide the build's progress.
         "-Wno-uninitialized", "-Wno-maybe-uninitialized"],
    ),
]
# Each object's compile time in seconds, taken once (GCC 12, torch 2.13) and
# used only for their order: the parallel build starts the longest first, so
# that no long object is left to the end.
COMPILE_SECONDS = {"csrc/cpu/kernel_default.cpp": 30, "csrc/cpu/kernel_avx2.cpp": 29, "csrc/cpu/kernel_avx512.cpp": 26,
                   "csrc/autograd.cpp": 19, "csrc/module.cpp": 18, UNITY_NAME: 14, "csrc/cpu/kernel_scalar.cpp": 12}

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


def write_build_info(package_dir):
    """torchrot/_build_info.py: the torch this extension is compiled against,
    which ``import torchrot`` compares with the running torch."""
    with open(os.path.join(package_dir, "_build_info.py"), "w") as f:
        f.write('"""Written by setup.py when it builds torchrot._C: the torch it was compiled against."""\n'
                f"TORCH_VERSION = {torch.__version__!r}\n")


def write_unity_source(path: str, members: list) -> str:
    """Writes the unity translation unit of ``members`` (an #include of each, by
    absolute path) at ``path``, unless it already holds that text (its time
    stamp then stays, and an incremental build does not recompile it)."""
    text = "// Generated by setup.py: the operator sources as one translation unit.\n" + "".join(
        f'#include "{os.path.abspath(member)}"\n' for member in members)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    if not os.path.exists(path) or open(path).read() != text:
        with open(path, "w") as f:
            f.write(text)
    return path


class BuildWithIsaKernels(BuildExtension):
    """Compiles the operator sources and each ISA kernel of the target (with its
    own flags) in one parallel build, then links them."""

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

        def optimization(source):
            x86_64_default = x86_64 and source == "csrc/cpu/kernel_default.cpp"
            return X86_64_DEFAULT_OPTIMIZATION if x86_64_default else KERNEL_OPTIMIZATION

        jobs = [(source, optimization(source) + flags + (GCC_FLAGS.get(source, []) if gcc else []))
                for source, flags in kernels]
        unity_members = [source for source in ext.sources if source in UNITY_SOURCES]
        unity = write_unity_source(os.path.join(self.build_temp, UNITY_NAME), unity_members)
        jobs += [(source, OPERATOR_OPTIMIZATION) for source in ext.sources if source not in unity_members]
        jobs += [(unity, OPERATOR_OPTIMIZATION)]
        workers = int(os.environ.get("MAX_JOBS") or os.cpu_count() or 1)
        print(f"torchrot: compiling {len(jobs)} objects ({', '.join(os.path.basename(s) for s, _ in kernels)} "
              f"and the operators), {workers} at a time; OpenMP "
              f"{'on' if openmp else 'off (at::parallel_for is serial)'}", flush=True)
        start = time.monotonic()
        done = []

        def compile_one(job):
            source, flags = job
            began = time.monotonic()
            # Each object in a folder of its own: torch's compile writes a
            # build.ninja per call, which concurrent calls must not share.
            folder = os.path.join(self.build_temp, os.path.splitext(os.path.basename(source))[0])
            objects = self.compiler.compile([source], output_dir=folder, include_dirs=ext.include_dirs,
                                            extra_postargs=list(cxx) + flags + SANITIZE_FLAGS,
                                            depends=ext.depends)
            done.append(source)
            what = f"{len(unity_members)} operator sources ({UNITY_NAME})" if source == unity else source
            print(f"torchrot: [{len(done)}/{len(jobs)}] {what} compiled in {time.monotonic() - began:.0f} s",
                  flush=True)
            return objects

        ordered = sorted(jobs, key=lambda job: -COMPILE_SECONDS.get(UNITY_NAME if job[0] == unity else job[0], 0))
        with ThreadPoolExecutor(max_workers=workers) as pool:
            compiled = dict(zip((source for source, _ in ordered), pool.map(compile_one, ordered)))
        # The unity object stands for its members (linked once, with the first).
        for index, member in enumerate(unity_members):
            compiled[member] = compiled[unity] if index == 0 else []
        # Linked as before: the operator objects, then the kernel objects
        # (baseline first, see above). setuptools' build_extension compiles
        # ext.sources and links: its compile call is served the objects built here.
        ext.extra_objects = [obj for source, _ in kernels for obj in compiled[source]] + list(ext.extra_objects or [])
        compile_sources = self.compiler.compile
        self.compiler.compile = lambda sources, *args, **kwargs: [obj for s in sources for obj in compiled[s]]
        try:
            super().build_extension(ext)
        finally:
            self.compiler.compile = compile_sources
        print(f"torchrot: extension built in {time.monotonic() - start:.0f} s", flush=True)
        # Beside the extension (what a wheel packages) and in the source tree
        # (what editable installs and in-place builds import).
        for package_dir in {os.path.dirname(self.get_ext_fullpath(ext.name)), "torchrot"}:
            write_build_info(package_dir)


setup(
    ext_modules=[
        CppExtension(
            name="torchrot._C",
            sources=OPERATOR_SOURCES,
            depends=sorted(glob.glob("csrc/**/*.h", recursive=True)),
            extra_compile_args=COMMON_FLAGS,
            extra_link_args=["-fopenmp"] + SANITIZE_FLAGS,
        )
    ],
    install_requires=[f"torch=={TORCH_RELEASE[0]}.{TORCH_RELEASE[1]}.*", "numpy"],
    cmdclass={"build_ext": BuildWithIsaKernels},
)
