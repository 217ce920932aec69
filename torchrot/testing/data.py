"""Test and benchmark data: matrix distributions, warm starts, point sets,
and the layouts a solver keeps its matrices in. Every generator is
deterministic in its seed and builds float64 matrices (cast afterwards if
needed)."""
from __future__ import annotations

import math
from typing import Callable

import torch

from torchrot.reference import cayley_rotation

__all__ = ['Generator', 'soa_view', 'tiled_view', 'rotations', 'random_rotations', 'registration_problem', 'random_spd', 'DISTRIBUTIONS', 'WELL_CONDITIONED', 'make_matrices', 'edge_case_matrices', 'make_warm_start', 'DEGENERATE_FAMILIES', 'make_degenerate_matrices']


Generator = Callable[[int, torch.Generator], torch.Tensor]

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
