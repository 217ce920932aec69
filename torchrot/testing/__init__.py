"""What the tests and the benchmarks share, so that speed is always measured
on the same data that correctness is checked on:

- :mod:`torchrot.testing.data`: matrix distributions, warm starts, point
  sets, and the layouts a solver keeps its matrices in;
- :mod:`torchrot.testing.metrics`: accuracy against the float64 SVD and the
  acceptance criteria;
- :mod:`torchrot.testing.kernels`: running a chosen CPU kernel object, or
  the device-generic kernels on CPU tensors.

Convention: the answer R* maximises tr(R^T M) (column vectors; M = sum w y x^T
gives R x ~ y); ``rotation_svd`` in float64 is the reference.
"""
from torchrot.reference import rotation_svd
from torchrot.testing import data, metrics
from torchrot.testing.data import *  # noqa: F403
from torchrot.testing.data import __all__ as _data
from torchrot.testing.kernels import *  # noqa: F403
from torchrot.testing.kernels import __all__ as _kernels
from torchrot.testing.metrics import *  # noqa: F403
from torchrot.testing.metrics import __all__ as _metrics

__all__ = [*_data, *_kernels, *_metrics, "rotation_svd"]

# The tables again, by assignment: the documentation reads the "#:" comments
# of assignments in the module it documents (torchrot.testing), not of imports.

#: Name → generator ``(n, torch.Generator) -> (n, 3, 3)`` float64 tensor, the
#: distributions every accuracy test and benchmark table runs on: ``warm`` and
#: ``warm_cond1e5`` (small remaining rotations times an SPD stretch of
#: condition number 1e3 or 1e5, the paper's warm-start solver data),
#: ``rot60``, ``rot180``, ``rot180_exact``, ``uniform``, ``gaussian``,
#: ``det_negative``, ``rank2``, ``rank1``, ``ill_conditioned``, ``symmetric``,
#: ``tiny`` (×1e-30) and ``huge`` (×1e30). :func:`make_matrices` draws from them.
DISTRIBUTIONS: dict = data.DISTRIBUTIONS
#: The names of the :data:`DISTRIBUTIONS` whose optimal rotation is unique
#: and well conditioned, where the fitted R itself is compared with the
#: SVD's (a tuple of str).
WELL_CONDITIONED: tuple = data.WELL_CONDITIONED
#: Name → generator of float64 ``(n, 3, 3)`` matrices where the derivative of
#: R(M) degenerates (repeated singular values, σᵢ + σⱼ ≈ 0, rank deficiency,
#: zero, extreme scales): the autograd tests fuzz the backward on these.
#: :func:`make_degenerate_matrices` draws from them.
DEGENERATE_FAMILIES: dict = data.DEGENERATE_FAMILIES
#: The acceptance criteria per dtype (``torch.float32``, ``torch.float64``)
#: that the tests apply to every distribution: the largest orthonormality
#: error, determinant error and relative objective shortfall against the
#: float64 SVD, as :func:`rotation_errors` measures them.
CRITERIA: dict = metrics.CRITERIA
