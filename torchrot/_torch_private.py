"""Every private torch name torchrot uses, in one place.

torch has no public API for what these do; any of them can move or change in
a torch release. tests/test_torch_private.py checks each one on the installed
torch (CI runs the whole suite on the oldest and the newest supported
release), so that a move fails there, loudly, before it reaches a user.
torchrot's other modules import these names from here, never from torch's
private modules. (The C++ side's are in csrc/torch_internals.h.)

What they are for: the operators' Python Autograd kernel records derivatives
at each torch.func level itself (torchrot/_autograd.py), which takes the
dispatch and functorch internals below; the fake kernel asks a symbolic
tensor whether it is dense; rigid_registration asks whether a device has
autocast also where torch 2.11's dynamo traces it.
"""
from __future__ import annotations

import contextlib

import torch
from torch._functorch.utils import enable_single_level_autograd_function, unwrap_dead_wrappers
from torch.autograd.function import _SingleLevelFunction

from torchrot._extension import torch_release

__all__ = [
    "after_autograd_keyset",
    "any_requires_grad",
    "autocast_available",
    "below_autograd",
    "enable_single_level_autograd_function",
    "forward_grad_enabled",
    "forward_grad_mode",
    "forward_level",
    "functorch_front_excluded",
    "functorch_transforms_active",
    "is_functorch_wrapped",
    "is_non_overlapping_and_dense",
    "single_level_function",
    "unwrap_dead_wrappers",
]

#: The dispatch keys after (below) the Autograd keys: an Autograd kernel
#: redispatches with ``keyset & after_autograd_keyset``.
after_autograd_keyset = torch._C._after_autograd_keyset
#: Whether any argument is a tensor that requires grad.
any_requires_grad = torch._C._any_requires_grad
#: Whether forward-mode AD records tangents (off inside a jvp rule).
forward_grad_enabled = torch._C._is_fwd_grad_enabled
#: Whether a torch.func transform (grad, vmap, jvp, ...) has a level open.
functorch_transforms_active = torch._C._are_functorch_transforms_active
_FUNCTORCH = torch._C._functorch
_FRONT_MODE = torch._C.DispatchKey.FuncTorchDynamicLayerFrontMode


def _autocast_available_constant(device_type: str) -> bool:
    return torch.amp.is_autocast_available(device_type)


# The mark torch.compiler.assume_constant_result sets (dynamo calls the
# function while tracing and takes its result as a constant), set without that
# decorator: it imports torch._dynamo, about 1 s on torchrot's import.
_autocast_available_constant._dynamo_marked_constant = True
#: torch.amp.is_autocast_available(device_type), also where torch.compile
#: traces it: torch 2.11's dynamo cannot trace the C function it calls
#: ("Attempted to call function marked as skipped", a graph break that
#: fullgraph=True refuses), so there it is a function marked constant; from
#: torch 2.12 on dynamo folds the call to a constant itself.
autocast_available = (
    _autocast_available_constant if torch_release(torch.__version__) < (2, 12) else torch.amp.is_autocast_available
)


def below_autograd() -> contextlib.AbstractContextManager:
    """A context in which operators run below their Autograd kernels
    (C++'s at::AutoDispatchBelowAutograd)."""
    return torch._C._AutoDispatchBelowAutograd()


def forward_grad_mode(enabled: bool) -> contextlib.AbstractContextManager:
    """A context in which forward-mode AD records tangents (``enabled``) or
    not, restoring the previous mode on exit (what torch.enable_grad is to
    reverse mode; torch.func's own single-level Functions turn it back on the
    same way)."""
    return torch.autograd.forward_ad._set_fwd_grad_enabled(enabled)


def forward_level() -> int:
    """The innermost open forward-AD dual level (-1: none), as
    ``torch.autograd.forward_ad.dual_level`` sets it (not torch.func.jvp's,
    nor one replayed by a tracer)."""
    return torch.autograd.forward_ad._current_level


def functorch_front_excluded() -> bool:
    """Whether torch.func's front dispatch key is excluded: code runs inside
    a transform's processing of an operator (an Autograd kernel or a jvp rule
    called for one level), not at the user's level."""
    return torch._C._dispatch_tls_is_dispatch_key_excluded(_FRONT_MODE)


def is_functorch_wrapped(t: torch.Tensor) -> bool:
    """Whether ``t`` is a torch.func wrapper (its values may be symbolic)."""
    return _FUNCTORCH.is_functorch_wrapped_tensor(t)


def is_non_overlapping_and_dense(t: torch.Tensor) -> bool:
    """Tensor.is_non_overlapping_and_dense (C++), also for fake tensors of
    symbolic shape (False where that cannot be decided)."""
    import torch._prims_common

    return torch._prims_common.is_non_overlapping_and_dense_or_false(t)


def single_level_function(function: type[torch.autograd.Function]) -> type:
    """``function`` as a single-level autograd function: the same forward,
    setup_context, backward and jvp, applied where an operator's Autograd
    kernel records a derivative for the one torch.func level that called it
    (under ``enable_single_level_autograd_function``) or outside torch.func.
    torch.autograd.Function.apply itself hands every call under a torch.func
    transform to torch's custom_function_call, which since torch 2.14 has no
    kernel below torch.func's own dispatch: inside an Autograd kernel it
    raised NotImplementedError for every transform. Its name is
    ``function``'s, so grad_fn names are unchanged. ``apply`` takes the
    forward's arguments complete and positional (no binding of defaults:
    that cost several times a small fit)."""
    members = {name: staticmethod(getattr(function, name)) for name in ("forward", "setup_context", "backward", "jvp")}
    members["__doc__"] = function.__doc__
    return type(function.__name__, (_SingleLevelFunction,), members)
