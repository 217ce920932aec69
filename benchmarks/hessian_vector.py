"""A Hessian-vector product through torchrot.fit_rotation beside the same
through torch.linalg.svd (torchrot.rotation_svd), in one process on the same
data.

The SVD's rotation is U diag(1, 1, sign det M) V^T with the sign detached
(torchrot.rotation_svd takes det(U V^T) instead, whose forward-over-reverse
derivative torch gives as NaN for about half of these matrices). The loss is
L(M) = sum_b <W_b, R(M_b)> over a batch of N matrices (gaussian,
torchrot.testing.make_matrices; W fixed), and the product H v is taken at M
along a random V two ways: reverse over reverse (the gradient of <grad L,
V>, torch.autograd.grad with create_graph=True: what double backward and
gradgradcheck do) and forward over reverse (torch.func.jvp of torch.func.grad:
torch.func.hessian's composition). Each case is timed interleaved with the
others (``--repeats`` rounds, ``torchrot.bench.timing.interleaved_median_seconds``),
and the table gives the median in ns per matrix and the SVD's time over
torchrot's. The products are checked to agree (well-separated singular
values: the gaussian data; the damping's relative (lambda / (sigma_i +
sigma_j))^2 apart) before anything is timed.

    python benchmarks/hessian_vector.py [--n 10000] [--repeats 7] [--dtype float64] [--threads 1]
"""
from __future__ import annotations

import argparse

import torch
from torch.func import grad, jvp

import torchrot
from torchrot.bench.machine import Load, load_average
from torchrot.bench.options import DTYPES, positive_int
from torchrot.bench.timing import interleaved_median_seconds
from torchrot.testing import make_matrices

__all__ = ["main"]



def _svd_rotation(M: torch.Tensor) -> torch.Tensor:
    """U diag(1, 1, sign det M) V^T, twice differentiable in every mode."""
    U, _, Vh = torch.linalg.svd(M)
    d = torch.linalg.det(M).sign().detach()
    D = torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1)
    return (U * D.unsqueeze(-2)) @ Vh


FITS = {"torchrot.fit_rotation": torchrot.fit_rotation, "torch.linalg.svd": _svd_rotation}


def _reverse_over_reverse(fit, M, W, V):
    x = M.detach().requires_grad_()
    (g,) = torch.autograd.grad((fit(x) * W).sum(), x, create_graph=True)
    return torch.autograd.grad((g * V).sum(), x)[0]


def _forward_over_reverse(fit, M, W, V):
    return jvp(grad(lambda x: (fit(x) * W).sum()), (M,), (V,))[1]


MODES = {"reverse over reverse": _reverse_over_reverse, "forward over reverse": _forward_over_reverse}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=positive_int, default=10_000, help="matrices per call")
    parser.add_argument("--repeats", type=positive_int, default=7, help="interleaved rounds (the median is printed)")
    parser.add_argument("--min-time", type=float, default=0.2, help="seconds of calls per sample")
    parser.add_argument("--dtype", choices=sorted(DTYPES), default="float64")
    parser.add_argument("--threads", type=positive_int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    dtype = DTYPES[args.dtype]
    gen = torch.Generator().manual_seed(1)
    M = make_matrices("gaussian", args.n, 0, dtype)
    W, V = (torch.randn(M.shape, generator=gen, dtype=torch.float64).to(dtype) for _ in range(2))
    cases = {}
    for mode, hvp in MODES.items():
        ours, svd = (hvp(fit, M, W, V) for fit in FITS.values())
        tolerance = 1e-6 if dtype == torch.float64 else 1e-2
        error = ((ours - svd).norm() / svd.norm()).item()
        if not error < tolerance:
            raise SystemExit(f"{mode}: torchrot's product differs from the SVD's by {error:.3g} (relative)")
        for name, fit in FITS.items():
            cases[(mode, name)] = lambda hvp=hvp, fit=fit: hvp(fit, M, W, V)
    before = load_average()
    seconds = interleaved_median_seconds(cases, args.repeats, args.min_time)
    print(f"Hessian-vector product of sum <W, R(M)>, gaussian M, {args.dtype}, N = {args.n}, {args.threads} "
          f"thread(s), CPU kernel {torch.ops.torchrot.cpu_kernel()}; median of {args.repeats} interleaved rounds; "
          f"{Load.around(before).line()}")
    print("| mode | method | ns/matrix | SVD / this |\n|---|---|---|---|")
    for (mode, name), s in seconds.items():
        svd = seconds[(mode, "torch.linalg.svd")]
        print(f"| {mode} | {name} | {s / args.n * 1e9:.0f} | {svd / s:.1f} |")


if __name__ == "__main__":
    main()
