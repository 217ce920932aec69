"""C sources of stand-in libraries for the CUDA libraries torch's aarch64 wheel links to.

PyPI's only Linux aarch64 torch==2.13.0 wheel is a CUDA build: even
libtorch_cpu.so needs libcudart.so.13 and libcupti.so.13, and libtorch.so
needs libtorch_cuda.so and so cuBLAS, cuDNN, NCCL and more (several GB, and
some of the pinned versions are not on the index). A CPU-only test never calls
them, so ``.ci/aarch64`` builds, for each missing soname, a small library of
that name defining every symbol the torch libraries import from it (with the
symbol version torch asks for: CUDA's libraries version each symbol by their
soname), plus every unversioned symbol nothing else defines. Each function
returns an error (100, cudaErrorNoDevice), except a few whose result is a
pointer or a count, so torch sees no CUDA device, as on a machine without one.
With TORCHROT_STUB_TRACE set, each stand-in names itself on stderr when called.

Usage: python aarch64_cuda_stubs.py TORCH_LIB SYSROOT OUT_DIR
writes OUT_DIR/SONAME.c and OUT_DIR/SONAME.map (its version script, empty
where torch asks for no version of it) for each missing SONAME and prints
the sonames, one per line. Host-side (readelf only; any architecture).
"""
from __future__ import annotations

import os
import re
import subprocess
import sys

SPECIAL = {  # functions whose generic "return 100" would be unsafe
    "cudaGetDeviceCount": "int cudaGetDeviceCount(int* n) { if (n) *n = 0; return 100; }",
    "cudaGetErrorString": 'const char* cudaGetErrorString(int e) { (void)e; return "no CUDA (stub)"; }',
    "cudaGetErrorName": 'const char* cudaGetErrorName(int e) { (void)e; return "cudaErrorNoDevice"; }',
    "cudaDriverGetVersion": "int cudaDriverGetVersion(int* v) { if (v) *v = 0; return 0; }",
    "cudaRuntimeGetVersion": "int cudaRuntimeGetVersion(int* v) { if (v) *v = 13000; return 0; }",
}


def readelf(*args: str) -> str:
    return subprocess.run(["readelf", "-W", *args], check=True, capture_output=True, text=True).stdout


def is_elf(path: str) -> bool:
    with open(path, "rb") as f:
        return f.read(4) == b"\x7fELF"


def shared_objects(directory: str) -> list[str]:
    if not os.path.isdir(directory):
        return []
    paths = (os.path.join(directory, f) for f in sorted(os.listdir(directory)))
    return [p for p in paths if ".so" in os.path.basename(p) and os.path.isfile(p) and is_elf(p)]


def dynamic_symbols(path: str):
    """(section, type, binding, name) of each dynamic symbol."""
    for line in readelf("--dyn-syms", path).splitlines():
        f = line.split()
        if len(f) >= 8 and f[0].endswith(":"):
            yield f[6], f[3], f[4], f[7]


def main() -> None:
    torch_lib, sysroot, out = sys.argv[1:4]
    system_dirs = [os.path.join(sysroot, d) for d in ("lib/aarch64-linux-gnu", "usr/lib/aarch64-linux-gnu")]
    torch_objects = shared_objects(torch_lib)
    present = {os.path.basename(p) for d in [torch_lib, *system_dirs] for p in shared_objects(d)}
    present |= {f for d in [torch_lib, *system_dirs] if os.path.isdir(d) for f in os.listdir(d)}  # symlinks

    missing: dict[str, dict[str, dict[str, str]]] = {}  # soname -> version -> symbol -> type
    for path in torch_objects:
        for soname in re.findall(r"\(NEEDED\)\s+Shared library: \[(.+?)\]", readelf("-d", path)):
            if soname not in present:
                missing.setdefault(soname, {})

    defined: set[str] = set()
    for path in torch_objects + [p for d in system_dirs for p in shared_objects(d)] + [
            os.path.join(sysroot, "usr/bin/python3.11")]:
        for section, _, binding, name in dynamic_symbols(path):
            if section != "UND" and binding in ("GLOBAL", "WEAK", "UNIQUE"):
                defined.add(name.split("@")[0])

    unversioned: dict[str, str] = {}
    for path in torch_objects:
        version_file, current = {}, None
        for line in readelf("-V", path).splitlines():
            m = re.search(r"File: (\S+)", line)
            if m:
                current = m.group(1)
                continue
            m = re.search(r"Name: (\S+)\s+Flags", line)
            if m and current:
                version_file[m.group(1)] = current
                if current in missing:  # every version needed of it must be defined
                    missing[current].setdefault(m.group(1), {})
        for section, typ, binding, name in dynamic_symbols(path):
            if section != "UND" or binding != "GLOBAL":
                continue  # weak references need no definition
            if "@" in name:
                symbol, version = name.split("@", 1)
                version = version.lstrip("@")
                library = version_file.get(version)
                if library in missing:
                    missing[library].setdefault(version, {})[symbol] = typ
            elif name not in defined:
                unversioned[name] = typ

    os.makedirs(out, exist_ok=True)
    for soname, versions in sorted(missing.items()):
        lines = [f"/* stand-in for {soname}: see .ci/aarch64_cuda_stubs.py */",
                 "#include <stdio.h>", "#include <stdlib.h>",
                 "static void traced(const char* name) {",
                 '  if (getenv("TORCHROT_STUB_TRACE")) fprintf(stderr, "stub called: %s\\n", name);', "}"]
        symbols = dict(unversioned)
        for table in versions.values():
            symbols.update(table)
        for symbol, typ in sorted(symbols.items()):
            if typ == "OBJECT":
                lines.append(f"char {symbol}[256];")
            elif symbol in SPECIAL:
                lines.append(SPECIAL[symbol])
            else:
                lines.append(f'long {symbol}(void) {{ traced("{symbol}"); return 100; }}')
        with open(os.path.join(out, soname + ".c"), "w") as f:
            f.write("\n".join(lines) + "\n")
        with open(os.path.join(out, soname + ".map"), "w") as f:
            for version, table in sorted(versions.items()):
                f.write(f"{version} {{ {''.join(f'{symbol}; ' for symbol in sorted(table))}}};\n")
        print(soname)


if __name__ == "__main__":
    main()
