"""The public fits whose contract the tests check on both: the rotation fit
(:func:`torchrot.fit_rotation`) and the orthogonal fit built on it
(:func:`torchrot.fit_orthogonal`), each with its float64 SVD reference, its
accuracy metrics and the words of its errors. Test modules parametrize over
:data:`FITS` (the ``fit`` fixture of conftest.py) rather than copying their
tests for the second fit.
"""
from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch

import torchrot
from torchrot.reference import orthogonal_svd, rotation_svd
from torchrot.testing import orthogonal_errors, rotation_errors

__all__ = ["FITS", "Fit"]


class Fit(NamedTuple):
    """A fit under test."""

    name: str
    fn: Callable[..., torch.Tensor]  #: the public function (M, init=None, *, max_iter, variant, gradient_eps, out)
    svd: Callable[[torch.Tensor], torch.Tensor]  #: its SVD answer (pass float64)
    errors: Callable[[torch.Tensor, torch.Tensor], dict]  #: its accuracy metrics against that answer
    orthogonal: bool  #: whether reflections are allowed (det -1 results, orthogonal warm starts)
    init_words: str  #: what its error says init must hold


FITS = {
    "fit_rotation": Fit("fit_rotation", torchrot.fit_rotation, rotation_svd, rotation_errors, False, "rotations"),
    "fit_orthogonal": Fit("fit_orthogonal", torchrot.fit_orthogonal, orthogonal_svd, orthogonal_errors, True,
                          "orthogonal matrices"),
}
