"""torchrot: fast, exact least-squares rotation fitting for PyTorch.

``fit_rotation(M)`` returns the rotation R (det R = +1) that maximises
tr(R^T M), i.e. the rotation nearest to M in the Frobenius norm. Column-vector
convention: for centred point sets, M = sum_i w_i y_i x_i^T gives R x_i ~ y_i.
"""
from importlib.metadata import PackageNotFoundError, version

import torch  # noqa: F401  (loads libtorch before the extension links to it)

from torchrot._extension import load_extension

_C = load_extension()  # registers torch.ops.torchrot.*; ImportError if built for another torch

# The CPU kernel is chosen once, now: TORCHROT_CPU_CAPABILITY is read here
# (a bad value fails the import with a ValueError naming it), never again.
torch.ops.torchrot.cpu_kernel()
# The operators' kernels registered in Python: derivatives (Autograd, vmap,
# autocast), fake kernels, and the kernels of devices without a native one.
# (I001: nn, the public submodule, is imported last, after what it wraps.)
from torchrot import _autograd, _constants, _device_kernels, _fake, _sharding  # noqa: E402, F401, I001
from torchrot._constants import FitStatus  # noqa: E402
from torchrot.fitting import FitInfo, fit_rotation, fit_rotation_info  # noqa: E402
from torchrot.orthogonal import fit_orthogonal  # noqa: E402
from torchrot.reference import fit_rotation_reference, rotation_svd  # noqa: E402
from torchrot.registration import RigidTransform, rigid_registration  # noqa: E402
from torchrot import nn  # noqa: E402

# DTensor's sharding strategies, as soon as torch.distributed.tensor is imported.
_sharding.install()

# An assignment, not an import, so that the documentation reads the comment
# (autodoc finds "#:" comments on assignments in the module it documents).
#: The default ``gradient_eps`` of :func:`torchrot.fit_rotation`, of
#: :class:`torchrot.nn.RotationFit` (``gradient_eps=None``) and of the operator
#: schemas, a float: the derivative's damping is ``lambda = gradient_eps |M|_F``
#: (see :doc:`derivative`). Read from the extension (csrc/limits.h).
DEFAULT_GRADIENT_EPS: float = _constants.GRADIENT_EPS

__all__ = [
    "DEFAULT_GRADIENT_EPS",
    "FitInfo",
    "FitStatus",
    "fit_orthogonal",
    "fit_rotation",
    "fit_rotation_info",
    "fit_rotation_reference",
    "nn",
    "RigidTransform",
    "rigid_registration",
    "rotation_svd",
]
try:
    __version__ = version("torchrot")  # defined once, in the package metadata (pyproject.toml)
except PackageNotFoundError:  # run from a source tree that was never installed
    __version__ = "unknown"
