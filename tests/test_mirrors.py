"""The algorithm is written once per language: csrc/kernel/ (C++), and its
twins torchrot.generic (PyTorch tensors) and torchrot.triton (Triton), file
for file and name for name. Every function of each header has a namesake in
the twin module of the same name, or is listed here with the reason it has
none: the correspondence is checked, not just described."""
from __future__ import annotations

import ast
import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
KERNEL = ROOT / "csrc" / "kernel"
# A function defined at a header's top level (inline, TORCHROT_INLINE, an attribute, or constexpr).
_FUNCTION = re.compile(r"^(?:template <[^\n]*>\n)?"
                       r"(?:TORCHROT_INLINE |inline |\[\[[^\]]*\]\] (?:inline )?|constexpr )"
                       r"[^\n(]*?\b([a-z][a-z_0-9]*)\(", re.M)

_FUSED = "torch's operations round every product and sum: nothing to fuse"
_LANE_ACCESS = "tensors index their lanes directly"
# Helpers of the AVX2 one-step kernel's register schedule (csrc/kernel/fit_rotation_impl.h,
# one_step_warm_from_memory): the same values as the functions they split up.
_SCHEDULE = {
    "mat3.h": {"transpose_times_by_rows": "transpose_times in another order of evaluation (same roundings)"},
    "cayley.h": {"rotate_row_by": "rotate_by, one row at a time"},
    "optimality.h": {"needs_cleaning": "clean_warm_start's mask of the lanes it changes"},
    "fit_rotation_impl.h": {
        "count_step": "take_step's bookkeeping",
        "one_step_warm_from_memory": "begin_fit and advance_one_step reading M and init from memory where "
                                     "they are used (16 vector registers): the same values",
    },
}
#: mirror -> {header: {function: why it has no twin}} ("*": the whole header).
NO_TWIN = {
    "generic": {
        "force_inline.h": {"*": "torch's operations are not inlined by hand"},
        "mul_add.h": {"*": _FUSED},
        "lanes.h": {"mul_add": _FUSED, "extract_lane": _LANE_ACCESS, "insert_lane": _LANE_ACCESS},
        "horn_fallback.h": {"jacobi_eigen4": "torch.linalg.eigh solves Horn's eigenproblem"},
        "fit_rotation_impl.h": {
            "begin_fit": "driver._fit_core begins the fit on whole tensors (normalisation, start)",
            "advance_one_step": "the one-step update is advance with max_iter = 1 (schedule.fit_soa)",
            "solve_fallback_lanes": "finish solves the fallback lanes (a masked update)",
            **_SCHEDULE["fit_rotation_impl.h"],
        },
        **{h: f for h, f in _SCHEDULE.items() if h != "fit_rotation_impl.h"},
    },
    "triton": {
        "force_inline.h": {"*": "Triton inlines every @triton.jit function"},
        "lanes.h": {"mul_add": "mul_add.py: tl.fma on lane tensors", "extract_lane": _LANE_ACCESS,
                    "insert_lane": _LANE_ACCESS},
        "horn_fallback.h": {"*": "the fallback's rare lanes leave the kernel: torchrot.generic.horn_fallback"},
        "quaternion.h": {"*": "only the fallback uses it: torchrot.generic.quaternion"},
        "fit_rotation_impl.h": {
            "solve_fallback_lanes": "torchrot.triton.operators.solve_fallback_lanes, outside the kernel",
            **_SCHEDULE["fit_rotation_impl.h"],
        },
        **{h: f for h, f in _SCHEDULE.items() if h != "fit_rotation_impl.h"},
    },
}
MIRRORS = tuple(NO_TWIN)


def _header_functions() -> dict[str, list[str]]:
    return {h.name: list(dict.fromkeys(_FUNCTION.findall(h.read_text()))) for h in sorted(KERNEL.glob("*.h"))}


def _module_functions(mirror: str, header: str) -> set[str] | None:
    """The functions of torchrot/<mirror>/<header stem>.py (read, not imported:
    Triton need not be installed), or None if there is no such module."""
    path = ROOT / "torchrot" / mirror / f"{pathlib.Path(header).stem}.py"
    if not path.exists():
        return None
    return {node.name for node in ast.parse(path.read_text()).body if isinstance(node, ast.FunctionDef)}


HEADERS = _header_functions()


def test_headers_are_read():
    assert HEADERS["cayley.h"][:2] == ["trace", "skew_vector"]
    assert "solve_fallback_lanes" in HEADERS["fit_rotation_impl.h"]
    assert sum(map(len, HEADERS.values())) > 40


@pytest.mark.parametrize("mirror", MIRRORS)
@pytest.mark.parametrize("header", sorted(HEADERS))
def test_every_function_has_its_twin(mirror, header):
    reasons = NO_TWIN[mirror].get(header, {})
    functions = _module_functions(mirror, header)
    if "*" in reasons:
        assert functions is None, f"torchrot/{mirror}/{pathlib.Path(header).stem}.py exists: drop the '*' entry"
        return
    assert functions is not None, f"csrc/kernel/{header} has no twin torchrot/{mirror}/{pathlib.Path(header).stem}.py"
    missing = [name for name in HEADERS[header] if name not in functions and name not in reasons]
    assert not missing, f"torchrot/{mirror}/{pathlib.Path(header).stem}.py lacks {missing} of csrc/kernel/{header}"
    stale = [name for name in reasons if name in functions or name not in HEADERS[header]]
    assert not stale, f"NO_TWIN lists {stale} for {mirror}/{header}, which have twins or are gone from the header"


@pytest.mark.parametrize("mirror", MIRRORS)
def test_no_reason_for_a_missing_header(mirror):
    assert set(NO_TWIN[mirror]) <= set(HEADERS)
