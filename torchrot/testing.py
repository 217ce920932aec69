"""Test and benchmark data: matrix distributions and accuracy metrics.

Shared by ``tests/`` and ``benchmarks/`` so that speed is always measured on the
same data that correctness is checked on. Every generator is deterministic in
its seed and builds float64 matrices (cast afterwards if needed).

Convention: the answer R* maximises tr(R^T M) (column vectors; M = sum w y x^T
gives R x ~ y); ``rotation_svd`` in float64 is the reference.
"""
from __future__ import annotations

import contextlib
import math
import warnings
from typing import Callable, Iterator

import torch

from torchrot.reference import cayley_rotation, rotation_svd

Generator = Callable[[int, torch.Generator], torch.Tensor]

def dtype_id(dtype: torch.dtype) -> str:
    """``"float32"`` for torch.float32: test ids and messages."""
    return str(dtype).removeprefix("torch.")


_INTEGER_VIEW = {torch.float32: torch.int32, torch.float64: torch.int64, torch.float16: torch.int16,
                 torch.bfloat16: torch.int16}


def bits(t: torch.Tensor) -> torch.Tensor:
    """The bits of a float tensor as integers (contiguous), for bit-for-bit
    comparisons in which NaN payloads and signed zeros count; other dtypes
    are returned as they are."""
    t = t.contiguous()
    return t.view(_INTEGER_VIEW[t.dtype]) if t.dtype in _INTEGER_VIEW else t


def soa_view(t: torch.Tensor) -> torch.Tensor:
    """t's values ``(N, 3, 3)`` in structure-of-arrays layout: a new (3, 3, N)
    tensor permuted to (N, 3, 3), the matrix index fastest (the layout of a
    solver's vectorised covariances, which the kernels load as plain vectors)."""
    return t.permute(1, 2, 0).contiguous().permute(2, 0, 1)


def tiled_view(t: torch.Tensor, tile: int) -> torch.Tensor:
    """t's values ``(N, 3, 3)`` in a tiled layout, ``(N / tile, tile, 3, 3)``:
    tiles of ``tile`` matrices, each in structure of arrays (a new
    ``(N / tile, 3, 3, tile)`` tensor permuted; tile 8 is the paper authors'
    AVX layout). The kernels load tiles at least a SIMD block wide as plain
    vectors and narrower ones in runs. N must be a multiple of ``tile``."""
    return t.reshape(-1, tile, 3, 3).permute(0, 2, 3, 1).contiguous().permute(0, 3, 1, 2)


def rotations(shape: int | tuple[int, ...], seed: int = 0, dtype: torch.dtype = torch.float64,
              max_angle: float = math.pi) -> torch.Tensor:
    """``(*shape, 3, 3)`` random rotations (angles up to ``max_angle``) from
    seed ``seed``, in ``dtype``: :func:`random_rotations` in any batch shape."""
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    n = math.prod(shape)
    return random_rotations(n, torch.Generator().manual_seed(seed), max_angle).reshape(*shape, 3, 3).to(dtype)


#: The CPU kernel objects, lowest level first.
CPU_KERNELS = ("scalar", "default", "avx2", "avx512")


def rounds_like_scalar(name: str) -> bool:
    """Whether CPU kernel ``name`` (capped at this CPU, as :func:`cpu_kernel`
    caps it) gives the scalar kernel's results bit for bit: it rounds
    ``a * b + c`` once, as the scalar kernel does. False only for x86-64's
    "default" kernel, the one for CPUs without AVX2 and FMA
    (csrc/kernel/mul_add.h); it meets the same accuracy criteria and is
    bit-identical across its own batch sizes, layouts and threads."""
    with cpu_kernel(name):
        return bool(torch.ops.torchrot._cpu_kernel_fuses_multiply_add())


def rounding_reference(name: str) -> str:
    """The kernel whose results CPU kernel ``name`` reproduces bit for bit:
    "scalar", or ``name`` itself where it rounds differently
    (:func:`rounds_like_scalar`)."""
    return "scalar" if rounds_like_scalar(name) else name


@contextlib.contextmanager
def cpu_kernel(name: str | None) -> Iterator[str]:
    """``with cpu_kernel("scalar") as used: ...`` runs the calling thread's
    torchrot calls on the CPU kernel object ``name`` (one of CPU_KERNELS,
    case-insensitive), capped at what this CPU supports; ``None`` runs the
    process-wide choice. ``used`` is the kernel that runs
    (``torch.ops.torchrot.cpu_kernel()``). Other threads keep theirs: the
    choice is per thread, so this is safe in multi-threaded tests. Nests.

    The process-wide choice is the environment variable
    TORCHROT_CPU_CAPABILITY, read once when torchrot is imported.
    Raises ValueError for an unknown name.
    """
    previous = torch.ops.torchrot._set_cpu_kernel(name or "")
    try:
        yield torch.ops.torchrot.cpu_kernel()
    finally:
        torch.ops.torchrot._set_cpu_kernel(previous)


def available_cpu_kernels() -> tuple[str, ...]:
    """The CPU kernel objects of CPU_KERNELS that this machine runs: those its
    build has (scalar and default everywhere, AVX2 and AVX-512 on x86-64) up
    to the highest its CPU supports."""
    found = []
    for name in CPU_KERNELS:
        with cpu_kernel(name) as used:
            if used == name:
                found.append(name)
    return tuple(found)


def conditioning(M: torch.Tensor) -> torch.Tensor:
    """Per matrix, how much rounding can move the fitted rotation:
    |M|_F / min(s_i + s_j) over the signed singular values s of M (the
    eigenvalues of the optimality system, csrc/kernel/rotation_gradient.h;
    Inf where the maximiser is not unique). A fit at working precision is
    within about eps times this of the exact rotation, in float64."""
    M = M.double()
    s = torch.linalg.svdvals(M)
    s[..., 2] = s[..., 2] * torch.linalg.det(M).sign()
    pair_sums = torch.stack([s[..., 0] + s[..., 1], s[..., 0] + s[..., 2], s[..., 1] + s[..., 2]], -1)
    return M.norm(dim=(-2, -1)) / pair_sums.amin(-1).clamp_min(0)


@contextlib.contextmanager
def generic_kernel() -> Iterator[None]:
    """``with generic_kernel(): ...`` runs ``torch.ops.torchrot.*`` on CPU
    tensors with the device-generic kernels (pure PyTorch, what CUDA, XPU and
    MPS tensors run) instead of the C++ ones, so that the same tests check
    both paths on any machine. Process-wide while it lasts (it registers
    CPU kernels that shadow the C++ ones; leaving restores them): not for
    multi-threaded use.
    """
    from torchrot._ops import GENERIC_KERNELS

    library = torch.library.Library("torchrot", "IMPL")
    try:
        with warnings.catch_warnings():
            # "Overriding a previously registered kernel": that is the point.
            warnings.filterwarnings("ignore", message=".*(Overriding a previously registered kernel|operators may also be overridden)")
            for name, kernel in GENERIC_KERNELS.items():
                library.impl(name, kernel, "CPU")
        yield
    finally:
        library._destroy()


def random_rotations(
    n: int, gen: torch.Generator, max_angle: float = math.pi, concentration: float = 1.0
) -> torch.Tensor:
    """``(n, 3, 3)`` rotations with uniform random axes and angles
    ``max_angle * u**concentration``, u uniform in [0, 1] (concentration > 1
    crowds the angles towards 0, like the solver data of the paper's Fig. 5)."""
    axis = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = torch.rand(n, generator=gen, dtype=torch.float64) ** concentration * max_angle
    return cayley_rotation(axis * torch.tan(angle / 2).unsqueeze(-1))


def registration_problem(batch: tuple[int, ...] = (), n: int = 40, seed: int = 0, noise: float = 0.0,
                         dtype: torch.dtype = torch.float64, with_scale: bool = True):
    """Points ``x`` ``(*batch, n, 3)``, a known transform ``(R, t, s)`` (float64;
    s = 1 unless with_scale) and ``y = s R x + t``, plus Gaussian noise of
    standard deviation ``noise``; x and y are cast to ``dtype``. x is spread
    anisotropically (3, 2, 1) around (1, 1, 1). Returns ``(x, y, (R, t, s))``."""
    gen = torch.Generator().manual_seed(seed)
    count = math.prod(batch)
    R = random_rotations(count, gen).reshape(*batch, 3, 3)
    t = torch.randn(*batch, 3, generator=gen, dtype=torch.float64) * 3
    s = (torch.rand(batch, generator=gen, dtype=torch.float64) * 2 + 0.5) if with_scale \
        else torch.ones(batch, dtype=torch.float64)
    x = torch.randn(*batch, n, 3, generator=gen, dtype=torch.float64) * torch.tensor([3.0, 2.0, 1.0]) + 1.0
    y = s[..., None, None] * (x @ R.mT) + t.unsqueeze(-2)
    y = y + noise * torch.randn(y.shape, generator=gen, dtype=torch.float64)
    return x.to(dtype), y.to(dtype), (R, t, s)


def random_spd(n: int, gen: torch.Generator, cond: float) -> torch.Tensor:
    """``(n, 3, 3)`` symmetric positive definite stretches with condition number
    ``cond``: eigenvalues 1, cond and one log-uniform between, random eigenbasis."""
    Q = random_rotations(n, gen)
    log_mid = torch.rand(n, generator=gen, dtype=torch.float64) * math.log(cond)
    eig = torch.stack([torch.ones(n, dtype=torch.float64), torch.full((n,), float(cond)), log_mid.exp()], -1)
    return Q @ torch.diag_embed(eig) @ Q.mT


def _with_singular_values(n: int, gen: torch.Generator, sigma: torch.Tensor) -> torch.Tensor:
    U, V = random_rotations(n, gen), random_rotations(n, gen)
    return U @ torch.diag_embed(sigma) @ V.mT


def _warm(cond: float, max_angle: float, concentration: float = 1.0) -> Generator:
    return lambda n, gen: random_rotations(n, gen, max_angle, concentration) @ random_spd(n, gen, cond)


def _gaussian_det_negative(n: int, gen: torch.Generator) -> torch.Tensor:
    G = torch.randn(n, 3, 3, generator=gen, dtype=torch.float64)
    flip = torch.linalg.det(G) > 0
    G[flip, 0] *= -1
    return G


def _rank2(n: int, gen: torch.Generator) -> torch.Tensor:
    sigma = torch.rand(n, 3, generator=gen, dtype=torch.float64) + 0.1
    sigma[:, 2] = 0
    return _with_singular_values(n, gen, sigma)


def _rank1(n: int, gen: torch.Generator) -> torch.Tensor:
    a = torch.randn(n, 3, 1, generator=gen, dtype=torch.float64)
    b = torch.randn(n, 1, 3, generator=gen, dtype=torch.float64)
    return a @ b


def _ill_conditioned(n: int, gen: torch.Generator) -> torch.Tensor:
    """Condition numbers 1e3..1e7, det of either sign."""
    log_cond = 3 + 4 * torch.rand(n, generator=gen, dtype=torch.float64)
    smallest = 10.0 ** (-log_cond)
    middle = smallest ** torch.rand(n, generator=gen, dtype=torch.float64)
    sign = torch.where(torch.rand(n, generator=gen, dtype=torch.float64) < 0.5, -1.0, 1.0)
    sigma = torch.stack([torch.ones(n, dtype=torch.float64), middle, sign * smallest], -1)
    return _with_singular_values(n, gen, sigma)


def _scaled(base: Generator, scale: float) -> Generator:
    return lambda n, gen: base(n, gen) * scale


def _symmetric(n: int, gen: torch.Generator) -> torch.Tensor:
    G = torch.randn(n, 3, 3, generator=gen, dtype=torch.float64)
    return G + G.mT


def _gaussian(n: int, gen: torch.Generator) -> torch.Tensor:
    return torch.randn(n, 3, 3, generator=gen, dtype=torch.float64)


def _uniform(n: int, gen: torch.Generator) -> torch.Tensor:
    return torch.rand(n, 3, 3, generator=gen, dtype=torch.float64)


#: name -> generator(n, torch.Generator) of float64 ``(n, 3, 3)`` matrices.
DISTRIBUTIONS: dict[str, Generator] = {
    # small remaining rotations (up to 15 degrees, median ~2) x SPD stretch of
    # condition number 1e3 or 1e5: the paper's warm-start solver data (Sec. 6.1)
    "warm": _warm(1e3, math.radians(15), concentration=3.0),
    "warm_cond1e5": _warm(1e5, math.radians(15), concentration=3.0),
    "rot60": _warm(10.0, math.radians(60)),
    "rot180": _warm(10.0, math.radians(179.9)),
    "rot180_exact": lambda n, gen: random_rotations(n, gen, math.radians(179.9)),
    "uniform": _uniform,
    "gaussian": _gaussian,
    "det_negative": _gaussian_det_negative,
    "rank2": _rank2,
    "rank1": _rank1,
    "ill_conditioned": _ill_conditioned,
    "symmetric": _symmetric,
    "tiny": _scaled(_gaussian, 1e-30),
    "huge": _scaled(_gaussian, 1e30),
}

#: Distributions whose optimal rotation is unique and well conditioned
#: (smallest sigma_i + sigma_j well away from 0), where R itself is compared.
WELL_CONDITIONED = ("warm", "rot60", "rot180", "rot180_exact", "uniform")


def make_matrices(name: str, n: int, seed: int = 0, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """``(n, 3, 3)`` matrices of distribution ``name`` (see DISTRIBUTIONS)."""
    if name not in DISTRIBUTIONS:
        raise ValueError(f"unknown distribution {name!r}; known: {sorted(DISTRIBUTIONS)}")
    gen = torch.Generator().manual_seed(seed)
    return DISTRIBUTIONS[name](n, gen).to(dtype)


def edge_case_matrices(dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Hand-picked matrices where iterative methods break: ``(k, 3, 3)``."""
    pi_x = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    gen = torch.Generator().manual_seed(1234)
    axis = torch.randn(4, 3, generator=gen, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    near_pi = cayley_rotation(axis * math.tan((math.pi - 1e-6) / 2))
    cases = [
        torch.zeros(3, 3, dtype=torch.float64),
        torch.eye(3, dtype=torch.float64),
        -torch.eye(3, dtype=torch.float64),
        torch.diag(torch.tensor([2.0, 2.0, 1.0], dtype=torch.float64)),
        torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)),
        torch.diag(torch.tensor([3.0, -2.0, -1.0], dtype=torch.float64)),
        torch.diag(torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)),
        torch.diag(torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64)),
        pi_x,
        torch.ones(3, 3, dtype=torch.float64),
        torch.tensor([[0.0, 1, 0], [0, 0, 1], [1, 0, 0]], dtype=torch.float64),
        torch.tensor([[1e30, 0, 0], [0, 1e-30, 0], [0, 0, 1e-30]], dtype=torch.float64),
        torch.full((3, 3), 1e-40, dtype=torch.float64),  # subnormal in float32
        *near_pi,
    ]
    return torch.stack(cases).to(dtype)


def objective(R: torch.Tensor, M: torch.Tensor) -> torch.Tensor:
    """tr(R^T M) per matrix, in float64."""
    return (R.double() * M.double()).sum((-2, -1))


def rotation_errors(R: torch.Tensor, M: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per-matrix accuracy of rotations R fitted to M, against float64 SVD.

    Returns float64 tensors of M's batch shape:
      orthonormality: max |R^T R - I|;
      det: |det R - 1|;
      shortfall: (tr(R*^T M) - tr(R^T M)) / |M|_F  (0 for M = 0);
      distance: |R - R*|_F (meaningful only where R* is unique).
    """
    Rd, Md = R.double(), M.double()
    eye = torch.eye(3, dtype=torch.float64)
    R_star = rotation_svd(Md)
    norm = Md.norm(dim=(-2, -1))
    safe = torch.where(norm > 0, norm, torch.ones_like(norm))
    return {
        "orthonormality": (Rd.mT @ Rd - eye).abs().amax((-2, -1)),
        "det": (torch.linalg.det(Rd) - 1).abs(),
        "shortfall": (objective(R_star, Md) - objective(Rd, Md)) / safe,
        "distance": (Rd - R_star).norm(dim=(-2, -1)),
    }


#: Acceptance criteria per dtype (issue #2): max orthonormality / det error
#: and max relative objective shortfall.
CRITERIA = {
    torch.float32: {"orthonormality": 1e-6, "det": 1e-6, "shortfall": 2e-6},
    torch.float64: {"orthonormality": 1e-13, "det": 1e-13, "shortfall": 1e-12},
}


def make_warm_start(name: str, n: int, seed: int = 0, dtype: torch.dtype = torch.float64):
    """``(M, init)`` as a local-global solver sees them: ``init`` holds random
    "previous" rotations and ``M = init @ M0`` with M0 from distribution
    ``name``, so the answer is ``init @ R*(M0)``: close to init for the warm
    distributions, where a warm-started one-step fit is accurate."""
    M0 = make_matrices(name, n, seed, torch.float64)
    init = random_rotations(n, torch.Generator().manual_seed(seed + 7919))
    return (init @ M0).to(dtype), init.to(dtype)


def _singular_value_family(sigma: Callable[[int, torch.Generator], torch.Tensor]) -> Generator:
    return lambda n, gen: _with_singular_values(n, gen, sigma(n, gen))


def _scaled_rotation(n: int, gen: torch.Generator) -> torch.Tensor:
    """s R: all three singular values equal (M = I is the special case)."""
    return random_rotations(n, gen) * (torch.rand(n, 1, 1, generator=gen, dtype=torch.float64) + 0.5)


def _sigma_repeated(n: int, gen: torch.Generator) -> torch.Tensor:
    a, b = torch.rand(2, n, generator=gen, dtype=torch.float64) + 0.1
    return torch.stack([a, a, b], -1)


def _sigma_half_turn(n: int, gen: torch.Generator) -> torch.Tensor:
    """sigma_2 + sigma_3 = 0 up to 1e-9..1: det < 0 and the fitted R is (near) a
    half-turn away from U V^T, where R is not (or barely) unique."""
    a = torch.rand(n, generator=gen, dtype=torch.float64) + 0.5
    gap = 10.0 ** (-9 * torch.rand(n, generator=gen, dtype=torch.float64))
    return torch.stack([a + 1, a, gap - a], -1)


#: name -> generator of float64 ``(n, 3, 3)`` matrices where the derivative of
#: R(M) degenerates: SVD-based gradients are NaN or unbounded there (repeated
#: singular values) and R(M) itself is not unique or barely (sigma_i + sigma_j
#: ~ 0). The autograd tests fuzz fit_rotation's backward on these.
DEGENERATE_FAMILIES: dict[str, Generator] = {
    "identity": lambda n, gen: torch.eye(3, dtype=torch.float64).expand(n, 3, 3).clone(),
    "scaled_rotation": _scaled_rotation,
    "repeated_sigma": _singular_value_family(_sigma_repeated),
    "half_turn": _singular_value_family(_sigma_half_turn),
    "rank2": _rank2,
    "rank1": _rank1,
    "zero": lambda n, gen: torch.zeros(n, 3, 3, dtype=torch.float64),
    "det_negative": _gaussian_det_negative,
    "ill_conditioned": _ill_conditioned,
    "tiny": _scaled(_gaussian, 1e-30),
    "huge": _scaled(_gaussian, 1e30),
}


def make_degenerate_matrices(name: str, n: int, seed: int = 0, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """``(n, 3, 3)`` matrices of family ``name`` of DEGENERATE_FAMILIES."""
    if name not in DEGENERATE_FAMILIES:
        raise ValueError(f"unknown family {name!r}; known: {sorted(DEGENERATE_FAMILIES)}")
    gen = torch.Generator().manual_seed(seed)
    return DEGENERATE_FAMILIES[name](n, gen).to(dtype)
