"""Test and benchmark data: matrix distributions, warm starts, point sets,
and the layouts a solver keeps its matrices in. Every generator is
deterministic in its seed and builds float64 matrices (cast afterwards if
needed)."""
from __future__ import annotations

import math
from collections.abc import Callable

import torch

from torchrot.reference import cayley_rotation

__all__ = ['Generator', 'soa_view', 'tiled_view', 'rotations', 'random_rotations', 'registration_problem',
           'random_spd', 'DISTRIBUTIONS', 'WELL_CONDITIONED', 'make_matrices', 'edge_case_matrices',
           'make_warm_start', 'DEGENERATE_FAMILIES', 'make_degenerate_matrices']


Generator = Callable[[int, torch.Generator], torch.Tensor]

def soa_view(t: torch.Tensor) -> torch.Tensor:
    """t's values ``(N, 3, 3)`` in structure-of-arrays layout: a new (3, 3, N)
    tensor permuted to (N, 3, 3), the matrix index fastest (the layout of a
    solver's vectorised covariances, which the kernels load as plain vectors).

    Args:
        t: ``(N, 3, 3)`` tensor, any dtype and device.

    Returns:
        A copy of t, its shape, dtype and device, with strides ``(1, 3 N, N)``.

    Examples:
        >>> from torchrot.testing import soa_view
        >>> M = torch.randn(5, 3, 3)
        >>> M_soa = soa_view(M)
        >>> torch.equal(M_soa, M), M_soa.stride()
        (True, (1, 15, 5))
    """
    return t.permute(1, 2, 0).contiguous().permute(2, 0, 1)

def tiled_view(t: torch.Tensor, tile: int) -> torch.Tensor:
    """t's values ``(N, 3, 3)`` in a tiled layout, ``(N / tile, tile, 3, 3)``:
    tiles of ``tile`` matrices, each in structure of arrays (a new
    ``(N / tile, 3, 3, tile)`` tensor permuted; tile 8 is the paper authors'
    AVX layout). The kernels load tiles at least a SIMD block wide as plain
    vectors and narrower ones in runs.

    Args:
        t: ``(N, 3, 3)`` tensor, any dtype and device; N a multiple of ``tile``.
        tile: matrices per tile, >= 1.

    Returns:
        A copy of t's values, shape ``(N / tile, tile, 3, 3)``, t's dtype and
        device, strides ``(9 tile, 1, 3 tile, tile)``; ``.reshape(N, 3, 3)``
        gives t back.

    Raises:
        RuntimeError: N is not a multiple of ``tile`` (from ``torch.reshape``:
            no partial tile is padded).

    Examples:
        >>> from torchrot.testing import tiled_view
        >>> M = torch.randn(16, 3, 3)
        >>> M_tiled = tiled_view(M, 8)
        >>> M_tiled.shape, M_tiled.stride(), torch.equal(M_tiled.reshape(16, 3, 3), M)
        (torch.Size([2, 8, 3, 3]), (72, 1, 24, 8), True)
        >>> tiled_view(torch.randn(10, 3, 3), 8)
        Traceback (most recent call last):
            ...
        RuntimeError: shape '[-1, 8, 3, 3]' is invalid for input of size 90
    """
    return t.reshape(-1, tile, 3, 3).permute(0, 2, 3, 1).contiguous().permute(0, 3, 1, 2)

def rotations(shape: int | tuple[int, ...], seed: int = 0, dtype: torch.dtype = torch.float64,
              max_angle: float = math.pi) -> torch.Tensor:
    """``(*shape, 3, 3)`` random rotations (angles up to ``max_angle``) from
    seed ``seed``, in ``dtype``: :func:`random_rotations` in any batch shape.

    Args:
        shape: the batch shape, an int or a tuple of ints.
        seed: seed of the CPU generator; the same seed gives the same rotations.
        dtype: the result's dtype (built in float64, then cast).
        max_angle: largest rotation angle, radians.

    Returns:
        ``(*shape, 3, 3)`` rotations on the CPU.

    Examples:
        >>> from torchrot.testing import rotations
        >>> R = rotations((2, 4), seed=0, dtype=torch.float32)
        >>> R.shape, R.dtype, torch.allclose(R.mT @ R, torch.eye(3).expand(2, 4, 3, 3), atol=1e-6)
        (torch.Size([2, 4, 3, 3]), torch.float32, True)
        >>> torch.equal(R, rotations((2, 4), seed=0, dtype=torch.float32))
        True
    """
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    n = math.prod(shape)
    return random_rotations(n, torch.Generator().manual_seed(seed), max_angle).reshape(*shape, 3, 3).to(dtype)

def random_rotations(
    n: int, gen: torch.Generator, max_angle: float = math.pi, concentration: float = 1.0
) -> torch.Tensor:
    """``(n, 3, 3)`` float64 rotations with uniform random axes and angles
    ``max_angle * u**concentration``, u uniform in [0, 1] (concentration > 1
    crowds the angles towards 0, like the solver data of the paper's Fig. 5),
    drawn from the CPU generator ``gen``.

    Examples:
        >>> import math
        >>> from torchrot.testing import random_rotations
        >>> R = random_rotations(100, torch.Generator().manual_seed(0), max_angle=math.radians(10))
        >>> angle = torch.arccos(((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1))  # tr R = 1 + 2 cos
        >>> R.dtype, bool((angle <= math.radians(10) + 1e-6).all())
        (torch.float64, True)
    """
    axis = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = torch.rand(n, generator=gen, dtype=torch.float64) ** concentration * max_angle
    return cayley_rotation(axis * torch.tan(angle / 2).unsqueeze(-1))

def registration_problem(batch: tuple[int, ...] = (), n: int = 40, seed: int = 0, noise: float = 0.0,
                         dtype: torch.dtype = torch.float64, with_scale: bool = True):
    """Points ``x`` ``(*batch, n, 3)``, a known transform ``(R, t, s)`` (float64;
    s = 1 unless with_scale) and ``y = s R x + t``, plus Gaussian noise of
    standard deviation ``noise``; x and y are cast to ``dtype``. x is spread
    anisotropically (3, 2, 1) around (1, 1, 1). Deterministic in ``seed``.

    Returns:
        ``(x, y, (R, t, s))``: x, y ``(*batch, n, 3)`` in ``dtype``; R
        ``(*batch, 3, 3)``, t ``(*batch, 3)`` and s ``(*batch)`` in float64; all on the CPU.

    Examples:
        >>> from torchrot.testing import registration_problem
        >>> x, y, (R, t, s) = registration_problem(batch=(2,), n=10, seed=0)
        >>> x.shape, R.shape, t.shape, s.shape
        (torch.Size([2, 10, 3]), torch.Size([2, 3, 3]), torch.Size([2, 3]), torch.Size([2]))
        >>> torch.allclose(y, s[:, None, None] * x @ R.mT + t[:, None, :])  # y_i = s R x_i + t
        True
    """
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
    """``(n, 3, 3)`` float64 symmetric positive definite stretches with
    condition number ``cond``: eigenvalues 1, cond and one log-uniform
    between, random eigenbasis, drawn from the CPU generator ``gen``.

    Examples:
        >>> from torchrot.testing import random_spd
        >>> S = random_spd(4, torch.Generator().manual_seed(0), cond=1e3)
        >>> eigenvalues = torch.linalg.eigvalsh(S)
        >>> torch.allclose(S, S.mT), (eigenvalues[:, -1] / eigenvalues[:, 0]).round().tolist()
        (True, [1000.0, 1000.0, 1000.0, 1000.0])
    """
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
    """``(n, 3, 3)`` matrices of distribution ``name`` of :data:`DISTRIBUTIONS`.

    Args:
        name: a key of :data:`DISTRIBUTIONS` (``"warm"``, ``"gaussian"``, ...).
        n: number of matrices.
        seed: seed of the CPU generator; the same seed gives the same matrices.
        dtype: the result's dtype: the matrices are built in float64, then cast.

    Returns:
        ``(n, 3, 3)`` tensor of ``dtype`` on the CPU.

    Raises:
        ValueError: ``name`` is not a key of :data:`DISTRIBUTIONS`.

    Examples:
        >>> from torchrot.testing import make_matrices
        >>> M = make_matrices("rank2", 4, seed=0)
        >>> M.shape, M.dtype, bool((torch.linalg.svdvals(M)[:, -1] < 1e-12).all())
        (torch.Size([4, 3, 3]), torch.float64, True)
        >>> make_matrices("warm", 4, dtype=torch.float32).dtype
        torch.float32
        >>> make_matrices("no_such_distribution", 4)
        Traceback (most recent call last):
            ...
        ValueError: unknown distribution 'no_such_distribution'; known: [...]
    """
    if name not in DISTRIBUTIONS:
        raise ValueError(f"unknown distribution {name!r}; known: {sorted(DISTRIBUTIONS)}")
    gen = torch.Generator().manual_seed(seed)
    return DISTRIBUTIONS[name](n, gen).to(dtype)

def edge_case_matrices(dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Hand-picked matrices where iterative methods break: ``(k, 3, 3)`` in
    ``dtype`` (built in float64, then cast), on the CPU: zero, +-I, repeated
    and zero singular values, reflections, rotations by pi and near it,
    extreme scales and float32 subnormals.

    Examples:
        >>> from torchrot.testing import edge_case_matrices
        >>> M = edge_case_matrices(torch.float32)
        >>> M.shape, M.dtype, bool(torchrot.fit_rotation(M).isfinite().all())
        (torch.Size([17, 3, 3]), torch.float32, True)
    """
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
    distributions, where a warm-started one-step fit is accurate.

    Returns:
        ``(M, init)``, both ``(n, 3, 3)`` in ``dtype`` (built in float64), on the CPU.

    Raises:
        ValueError: ``name`` is not a key of :data:`DISTRIBUTIONS`.

    Examples:
        >>> from torchrot.testing import make_warm_start
        >>> M, init = make_warm_start("warm", 8, seed=0)
        >>> R = torchrot.fit_rotation(M, init, max_iter=1)  # one Cayley step from init
        >>> R_best = torchrot.rotation_svd(M)
        >>> bool(((R - R_best).norm(dim=(-2, -1)) < (init - R_best).norm(dim=(-2, -1))).all())
        True
    """
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
    """``(n, 3, 3)`` matrices of family ``name`` of :data:`DEGENERATE_FAMILIES`.

    Args:
        name: a key of :data:`DEGENERATE_FAMILIES` (``"repeated_sigma"``, ...).
        n: number of matrices.
        seed: seed of the CPU generator; the same seed gives the same matrices.
        dtype: the result's dtype: the matrices are built in float64, then cast.

    Returns:
        ``(n, 3, 3)`` tensor of ``dtype`` on the CPU.

    Raises:
        ValueError: ``name`` is not a key of :data:`DEGENERATE_FAMILIES`.

    Examples:
        >>> from torchrot.testing import make_degenerate_matrices
        >>> M = make_degenerate_matrices("scaled_rotation", 3).requires_grad_()  # three equal singular values
        >>> torchrot.fit_rotation(M).sum().backward()
        >>> bool(M.grad.isfinite().all())
        True
    """
    if name not in DEGENERATE_FAMILIES:
        raise ValueError(f"unknown family {name!r}; known: {sorted(DEGENERATE_FAMILIES)}")
    gen = torch.Generator().manual_seed(seed)
    return DEGENERATE_FAMILIES[name](n, gen).to(dtype)
