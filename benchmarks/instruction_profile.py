"""Where a kernel's instructions per matrix go: by source function, with its vector moves and stack operands.

    TORCHROT_DEBUG_INFO=1 pip install --no-build-isolation --no-deps -e .   (debug information; same code)
    python benchmarks/instruction_profile.py "one-step, SoA views, out=" [more cases] [--kernel avx2] [--depth 2]
    python benchmarks/instruction_profile.py "paper authors: one-step, tiles of 8, in place" --authors PATH

Runs one case of ``instruction_counts.py`` (the same names, data and sizes) under
``instruction_counter.c`` with its trace on: the address of every instruction
the case executes in its region at N1 and at N2 matrices. The addresses in
torchrot's extension (or the authors' library) are joined with the debug
information (``addr2line -i``: the chain of inlined functions at each address)
and the disassembly (``objdump -d``), and the difference of the two regions
divided by N2 - N1 is charged per matrix to the function ``--depth`` levels
below the kernel's entry (``fit_range``, ``count_bad_warm_starts``...;
``--root`` names another): all instructions, ``vmov*`` (vector moves), and
instructions with a stack operand (addressed off ``%rsp`` or ``%rbp``: spills,
reloads and buffers on the stack). Work outside those libraries (Python,
torch's dispatch) is one row, which should be near zero per matrix. A first
table gives every case by part of the fit instead (PARTS: the warm-start
check, moving the matrices, the maximum check, the guarantees in the step,
the Cayley step, the lane state, the authors' kernels), side by side.

Why: the speed targets against the authors' AVX kernel (authors_kernel.py)
are reached or not by instructions and spills per matrix; this says which
part of the computation (scaling, the checks, S = R^T A, the step, the update,
the stores) costs what. x86-64 Linux, binutils' addr2line and objdump.
"""
from __future__ import annotations

import argparse
import collections
import os
import re
import subprocess
import sys
import tempfile

import instruction_counts
import numpy as np

ENTRY_POINTS = ("fit_range", "count_bad_warm_starts", "rotation_gradient_range", "fit_rotation_small_avx",
                "fit_rotation_avx")
OUTSIDE = "(outside the library: Python, torch)"
LAMBDA = "{lambda}"
# The parts of a fit that an instruction can belong to, each by the functions
# that make it up: an instruction belongs to the first part one of whose
# functions its chain of inlined functions holds (so a load inside the step
# is moving, a mask inside begin_fit a check), else to LOOP_PART.
PARTS = (
    ("the warm-start check before writing", ("count_bad_warm_starts",)),
    ("moving the matrices in and out", (
        "load", "loadu", "store", "storeu", "load_halves", "store_halves", "load_block", "store_block", "load_soa",
        "store_soa", "gather_block", "scatter_block", "load_tiled_runs", "store_tiled_runs", "prefetch_even_block",
        "prefetch_contiguous_block", "prefetch_tiles", "_mm256_load_ps", "_mm256_store_ps")),
    ("the maximum check (converged fits)", ("is_maximum", "saddle_escape_rotation")),
    ("scaling, the checks and the masks in the step", (
        "max_abs_entry", "unit_scale", "outside_normal_range", "check_warm_start", "clean_warm_start",
        "needs_cleaning", "can_take", "count_step", "finish")),
    ("the Cayley step (S = R^T A, the estimate, the step, R Q)", (
        "transpose_times", "transpose_times_by_rows", "trace", "objective_estimate", "cayley_step",
        "cayley_increment", "rotate_by", "rotate_row_by", "take_step")),
    ("the lane state and the convergence decisions", ("advance", "begin_fit", "LaneState", "save_running_lanes",
                                                      "restore_block")),
    # Their kernels are one function each (intrinsics inlined, loads and
    # stores by pointer), not parted as torchrot's.
    ("the paper authors' kernel: all of it (loads, step, stores; iterated: its test)",
     ("fit_rotation_small_avx", "fit_rotation_avx")),
)
LOOP_PART = "the loops over blocks, and the rest"

__all__ = ["ENTRY_POINTS", "LOOP_PART", "PARTS", "main", "profile", "short_name"]


def short_name(function: str) -> str:
    """A demangled C++ name without namespaces, template arguments or parameters;
    a lambda's call operator is ``{lambda}``."""
    function = re.sub(r" \[clone [^\]]*\]", "", function)
    if function.startswith("operator()"):  # an inlined lambda: addr2line names its call operator alone
        return LAMBDA
    out, depth = [], 0
    for ch in function:
        if ch in "<(":
            depth += 1
        elif ch in ">)" and depth:
            depth -= 1
        elif depth == 0:
            out.append(ch)
    parts = [p for p in "".join(out).replace(" const", "").split("::") if p]
    if parts and (parts[-1] == "operator" or parts[-1].startswith("{lambda")):
        # An out-of-line lambda keeps the name of the function it is defined in.
        enclosing = [q for q in parts if q != "operator" and not q.startswith("{lambda")]
        return f"{enclosing[-1].split()[-1]}::{LAMBDA}" if enclosing else LAMBDA
    return parts[-1].split()[-1] if parts else function


def _library_mapping(maps_path: str, library: str) -> list[tuple[int, int, int]]:
    """(start, end, file offset) of the executable mappings of ``library``."""
    real = os.path.realpath(library)
    spans = []
    for line in open(maps_path):
        fields = line.split()
        if len(fields) >= 6 and "x" in fields[1] and os.path.realpath(fields[5]) == real:
            start, end = (int(x, 16) for x in fields[0].split("-"))
            spans.append((start, end, int(fields[2], 16)))
    return spans


def _load_segments(library: str) -> list[tuple[int, int, int]]:
    """(file offset, virtual address, size) of the library's PT_LOAD segments."""
    out = subprocess.run(["readelf", "-lW", library], check=True, capture_output=True, text=True).stdout
    return [(int(f[1], 16), int(f[2], 16), int(f[4], 16)) for f in (line.split() for line in out.splitlines())
            if f and f[0] == "LOAD"]


def _to_library_addresses(pcs: np.ndarray, spans, segments) -> tuple[np.ndarray, int]:
    """The library's own (virtual) addresses of the pcs inside it, and how many fell outside."""
    inside = np.zeros(pcs.shape, dtype=bool)
    addresses = np.zeros(pcs.shape, dtype=np.uint64)
    for start, end, offset in spans:
        hit = (pcs >= start) & (pcs < end)
        file_offsets = pcs[hit] - np.uint64(start) + np.uint64(offset)
        vaddr = np.zeros(file_offsets.shape, dtype=np.uint64)
        for seg_offset, seg_vaddr, size in segments:
            in_segment = (file_offsets >= seg_offset) & (file_offsets < seg_offset + size)
            vaddr[in_segment] = file_offsets[in_segment] - np.uint64(seg_offset) + np.uint64(seg_vaddr)
        addresses[hit] = vaddr
        inside |= hit
    return addresses[inside], int((~inside).sum())


def _inline_chains(library: str, addresses: list[int]) -> dict[int, list[str]]:
    """address -> its functions, outermost first (addr2line -i: the inlined ones
    too), and last the source line of the instruction itself (file:line)."""
    out = subprocess.run(["addr2line", "-a", "-f", "-i", "-C", "-e", library, *map(hex, addresses)],
                         check=True, capture_output=True, text=True).stdout.splitlines()
    chains, current, i = {}, None, 0
    while i < len(out):
        line = out[i]
        if re.fullmatch(r"0x[0-9a-f]+", line):
            current = int(line, 16)
            chains[current] = []
            i += 1
            continue
        if not chains[current]:
            chains[current].append(os.path.basename(out[i + 1]).split(" ")[0])  # the innermost file:line
        chains[current].insert(0, short_name(line))  # its function (each next one is its caller)
        i += 2
    return chains


def _instructions(library: str, addresses: list[int]) -> dict[int, str]:
    """address -> its instruction in AT&T syntax (objdump -d, over the span of ``addresses``)."""
    out = subprocess.run(["objdump", "-d", "--no-show-raw-insn", "-M", "att", f"--start-address={min(addresses)}",
                          f"--stop-address={max(addresses) + 16}", library],
                         check=True, capture_output=True, text=True).stdout
    instructions = {}
    for line in out.splitlines():
        match = re.match(r"\s*([0-9a-f]+):\s+(.*)", line)
        if match:
            instructions[int(match.group(1), 16)] = match.group(2).strip()
    return instructions


def _charge(chain: list[str], depth: int, root: str | None, lines: bool) -> str:
    """The row an address's chain of functions is charged to: the ``depth``
    functions below ``root`` (else below the entry point), and the function a
    lambda there calls; with ``lines``, the source line of the instruction."""
    if lines:
        return chain[-1] if chain else "?"
    chain = chain[:-1]
    at = next((i for i, name in enumerate(chain) if name == root), None) if root else None
    prefix = []
    if at is None:  # rows below the entry point start with its name
        at = next((i for i, name in enumerate(chain) if name.split("::")[0] in ENTRY_POINTS), None)
        if at is None:
            return chain[0] if chain else "?"
        prefix = [chain[at]]
    below = chain[at + 1:at + 1 + depth]
    if below and below[-1] == LAMBDA and at + 1 + depth < len(chain):
        below.append(chain[at + 1 + depth])
    return " > ".join(prefix + below) if below else chain[at] + " (itself)"


def _part(chain: list[str]) -> str:
    """The part of PARTS that an address's chain of functions belongs to."""
    names = {name.split("::")[0] for name in chain[:-1]}  # an out-of-line lambda by its function's name
    return next((part for part, functions in PARTS if names.intersection(functions)), LOOP_PART)


def profile(trace_prefix: str, library: str, sizes: tuple[int, int], depth: int, root: str | None,
            lines: bool = False) -> tuple[dict, dict]:
    """{row: [instructions, vmov, stack operands] per matrix}, from regions 0 and 1 of a trace:
    by function (rows: see _charge), and by part of the fit (PARTS)."""
    histograms, outside = [], []
    for region in (0, 1):
        pcs = np.fromfile(f"{trace_prefix}.{region}.pcs", dtype=np.uint64)
        spans = _library_mapping(f"{trace_prefix}.{region}.maps", library)
        if not spans:
            sys.exit(f"{library} was not mapped in the traced process")
        addresses, n_outside = _to_library_addresses(pcs, spans, _load_segments(library))
        values, counts = np.unique(addresses, return_counts=True)
        histograms.append(dict(zip(values.tolist(), counts.tolist())))
        outside.append(n_outside)
    hot = sorted(set(histograms[0]) | set(histograms[1]))
    chains, instructions = _inline_chains(library, hot), _instructions(library, hot)
    per_matrix = 1.0 / (sizes[1] - sizes[0])
    rows = collections.defaultdict(lambda: [0.0, 0.0, 0.0])
    part_rows = collections.defaultdict(lambda: [0.0, 0.0, 0.0])
    for address in hot:
        executed = (histograms[1].get(address, 0) - histograms[0].get(address, 0)) * per_matrix
        text = instructions.get(address, "")
        chain = chains.get(address, [])
        counts = (executed, executed * text.startswith("vmov"), executed * bool(re.search(r"\(%r[sb]p", text)))
        for row in (rows[_charge(chain, depth, root, lines)], part_rows[_part(chain)]):
            for k in range(3):
                row[k] += counts[k]
    for grouping in (rows, part_rows):
        grouping[OUTSIDE][0] += (outside[1] - outside[0]) * per_matrix
    return dict(rows), dict(part_rows)


def _traced_rows(case: str, args, counter: str, libraries: dict, prefix: str) -> tuple[dict, dict, str]:
    """profile's rows of one case (by function, by part), in torchrot's library or,
    for the authors' cases, theirs, and the kernel it ran on."""
    library = libraries["authors" if case.startswith(instruction_counts.AUTHORS_PREFIX) else "torchrot"]
    worker = [counter, sys.executable, instruction_counts.__file__, "--worker", "--kernels", args.kernel,
              "--sizes", *map(str, args.sizes), "--repeats", "1", "--only", case]
    if "authors" in libraries:
        worker += ["--authors-library", libraries["authors"]]
    run = subprocess.run(worker, env={**os.environ, "INSTRUCTION_COUNTER_TRACE": prefix}, capture_output=True,
                         text=True)
    if run.returncode != 0 or not os.path.exists(f"{prefix}.1.pcs"):
        sys.exit(f"the traced worker failed (is {case!r} a case of instruction_counts.py?):\n{run.stderr}")
    ran = [line[len(instruction_counts.KERNEL_PREFIX):] for line in run.stderr.splitlines()
           if line.startswith(instruction_counts.KERNEL_PREFIX)]
    return (*profile(prefix, library, tuple(args.sizes), args.depth, args.root, args.lines), ran[0])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("cases", nargs="+", help="cases of instruction_counts.py, by name; a table each")
    parser.add_argument("--kernel", default=None, help="default: the kernel this machine dispatches to")
    parser.add_argument("--sizes", type=int, nargs=2, default=[512, 1536])
    parser.add_argument("--depth", type=int, default=1, help="levels of functions below the entry point per row")
    parser.add_argument("--root", help="charge to the functions below this one instead of the entry point")
    parser.add_argument("--lines", action="store_true", help="charge to source lines (file:line) instead")
    parser.add_argument("--authors", metavar="PATH", help="a checkout of ErisZhang/fast-rotation-fitting "
                        "(for the authors' cases, whose library is then the one profiled)")
    parser.add_argument("--eigen", default="/usr/include/eigen3")
    parser.add_argument("--march", default="haswell", help="the authors' kernels' -march (haswell: AVX2)")
    args = parser.parse_args()
    n1, n2 = args.sizes
    if min(n1, n2) < instruction_counts.MIN_SIZE or n1 >= n2 or n1 % 8 or n2 % 8:
        parser.error(f"--sizes N1 N2 needs {instruction_counts.MIN_SIZE} <= N1 < N2, multiples of 8")
    if args.authors is None and any(case.startswith(instruction_counts.AUTHORS_PREFIX) for case in args.cases):
        parser.error("the authors' cases need --authors")
    import torch

    import torchrot
    from torchrot.bench.machine import machine_info

    args.kernel = args.kernel or torch.ops.torchrot.cpu_kernel()
    with tempfile.TemporaryDirectory() as tmp:
        counter = instruction_counts.build_counter(tmp)
        libraries = {"torchrot": torchrot._C.__file__}
        if args.authors is not None:
            import authors_kernel

            libraries["authors"] = authors_kernel.compile_library(args.authors, args.eigen, tmp, args.march,
                                                                  debug_info=True)
        sections = subprocess.run(["readelf", "-SW", libraries["torchrot"]], check=True, capture_output=True,
                                  text=True).stdout
        if ".debug_info" not in sections:
            sys.exit(f"{libraries['torchrot']} has no debug information: build torchrot with TORCHROT_DEBUG_INFO=1")
        tables = {case: _traced_rows(case, args, counter, libraries, os.path.join(tmp, f"trace{i}"))
                  for i, case in enumerate(args.cases)}
    print(f"Machine: {machine_info()}\n")
    print(f"Per matrix, float32, 1 thread, ((N = {n2}) - (N = {n1})) / {n2 - n1}; the ARAP recording's warm data "
          f"(instruction_counts.py); stack operands: addressed off %rsp or %rbp"
          f"{f'; the authors kernels built with -march={args.march}' if args.authors else ''}; rows: the functions "
          f"{args.depth} level(s) below {f'{args.root} (where it runs, else below ' if args.root else '('}"
          "the kernel's entry point).")
    _print_parts(tables)
    for case, (rows, _, ran) in tables.items():
        print(f"\n{case} ({_whose(case, ran)}):\n")
        print("| function | instructions | vmov* | stack operands |\n|---|---|---|---|")
        for name, row in sorted(rows.items(), key=lambda item: -item[1][0]):
            if abs(row[0]) >= 0.05:
                print(f"| {name} | {row[0]:.1f} | {row[1]:.1f} | {row[2]:.1f} |")
        total = _total(rows)
        print(f"| (every instruction) | {total[0]:.1f} | {total[1]:.1f} | {total[2]:.1f} |")


def _whose(case: str, ran: str) -> str:
    return "the authors' kernel" if case.startswith(instruction_counts.AUTHORS_PREFIX) else f"kernel {ran}"


def _total(rows: dict) -> list[float]:
    return [sum(row[k] for row in rows.values()) for k in range(3)]


def _print_parts(tables: dict) -> None:
    """One table of every case by part of the fit (PARTS): instructions per
    matrix, and in brackets those with a stack operand."""
    cases = list(tables)
    print("\nBy part of the fit (PARTS in instruction_profile.py: an instruction belongs to the first part that one "
          "of the functions it was inlined from makes up), instructions per matrix (of which stack operands):\n")
    print("| part | " + " | ".join(f"{case} ({_whose(case, tables[case][2])})" for case in cases) + " |")
    print("|---" * (len(cases) + 1) + "|")
    for part in [name for name, _ in PARTS] + [LOOP_PART, OUTSIDE]:
        cells = []
        for case in cases:
            row = tables[case][1].get(part, [0.0, 0.0, 0.0])
            cells.append(f"{row[0]:.1f}" + ("" if part == OUTSIDE else f" ({row[2]:.1f})"))
        print(f"| {part} | " + " | ".join(cells) + " |")
    totals = [_total(tables[case][1]) for case in cases]
    print("| (every instruction) | " + " | ".join(f"{t[0]:.1f} ({t[2]:.1f})" for t in totals) + " |")


if __name__ == "__main__":
    main()
