"""Cross-compiles torchrot._C for Linux aarch64 with the checkout's own setup.py.

Run by ``.ci/aarch64`` with the host (x86-64) Python, in a copy of the
checkout: setup.py's BuildWithIsaKernels runs unchanged, with the compiler
(CC/CXX/LDSHARED, set by the caller to aarch64-linux-gnu-*) asked for its
target, and torch's extension helpers pointed at the aarch64 wheel's headers
and libraries instead of the host torch's; the arm64 Python headers come
first on the include path. The result, built as the host's extension suffix,
is renamed to the aarch64 one (Python's importer only looks for its own).

Usage: python .ci/aarch64_build.py TORCH_DIR PYTHON_INCLUDE_ROOT BUILD_LIB
  TORCH_DIR            the unpacked aarch64 wheel's torch/ folder
  PYTHON_INCLUDE_ROOT  the unpacked arm64 libpython3.11-dev's usr/include
  BUILD_LIB            where the package tree with torchrot/_C*.so goes
"""
from __future__ import annotations

import os
import runpy
import sys
import sysconfig

import torch.utils.cpp_extension as cpp_extension


def main() -> None:
    torch_dir, include_root, build_lib = (os.path.abspath(a) for a in sys.argv[1:4])
    cpp_extension._TORCH_PATH = torch_dir
    cpp_extension.TORCH_LIB_PATH = os.path.join(torch_dir, "lib")
    python_include = os.path.join(include_root, "python3.11")
    sys.argv = ["setup.py", "build_ext", "--build-lib", build_lib, "--build-temp", build_lib + ".tmp",
                "--include-dirs", os.pathsep.join([python_include, include_root])]
    runpy.run_path("setup.py", run_name="__main__")
    host_suffix = sysconfig.get_config_var("EXT_SUFFIX")
    built = os.path.join(build_lib, "torchrot", "_C" + host_suffix)
    target = os.path.join(build_lib, "torchrot", "_C.cpython-311-aarch64-linux-gnu.so")
    os.replace(built, target)
    print(f"aarch64 extension: {target}")


if __name__ == "__main__":
    main()
