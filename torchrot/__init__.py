"""torchrot: fast, exact least-squares rotation fitting for PyTorch.

``fit_rotation(M)`` returns the rotation R (det R = +1) that maximises
tr(R^T M), i.e. the rotation nearest to M in the Frobenius norm. Column-vector
convention: for centred point sets, M = sum_i w_i y_i x_i^T gives R x_i ~ y_i.
"""
import torch  # noqa: F401  (loads libtorch before the extension links to it)

from torchrot import _C  # noqa: F401  (registers torch.ops.torchrot.*)

# The CPU kernel is chosen once, now: TORCHROT_CPU_CAPABILITY is read here
# (a bad value fails the import with a ValueError naming it), never again.
torch.ops.torchrot.cpu_kernel()
from torchrot._ops import FitInfo, fit_rotation, fit_rotation_info  # also registers autograd (_autograd)
from torchrot.reference import fit_rotation_reference, rotation_svd
from torchrot.registration import RigidTransform, rigid_registration
from torchrot import nn  # noqa: E402  (after fit_rotation: nn calls torchrot.fit_rotation)

__all__ = [
    "FitInfo",
    "fit_rotation",
    "fit_rotation_info",
    "fit_rotation_reference",
    "nn",
    "RigidTransform",
    "rigid_registration",
    "rotation_svd",
]
__version__ = "0.1.0"
