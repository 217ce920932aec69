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
from torchrot.testing.data import *  # noqa: F403
from torchrot.testing.data import __all__ as _data
from torchrot.testing.kernels import *  # noqa: F403
from torchrot.testing.kernels import __all__ as _kernels
from torchrot.testing.metrics import *  # noqa: F403
from torchrot.testing.metrics import __all__ as _metrics

__all__ = [*_data, *_kernels, *_metrics, "rotation_svd"]
