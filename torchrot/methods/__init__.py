"""The paper's comparison methods (Table 1) as batched, plain PyTorch functions.

Every function takes ``(..., 3, 3)`` float32/float64 matrices M (any batch
shape, any strides) and returns the rotations R (det R = +1) maximising
tr(R^T M), i.e. the rotation nearest to M in the Frobenius norm: the same
convention as :func:`torchrot.fit_rotation`. Column vectors: for centred
point sets x_i, y_i, M = sum_i w_i y_i x_i^T gives R x_i ~ y_i. Results have
M's dtype and are computed in it (no hidden float64), so the benchmark
measures each method as a user of that dtype would run it.

Each is written from its paper's formulas; where a paper leaves something
open for general batched input (scale, guards), the docstring says what was
chosen. Warm-startable methods take ``init`` (rotations broadcastable to M,
e.g. the previous iteration's R) and an iteration count ``max_iter``
(``None`` = iterate each matrix until its step stalls, under a cap).

Accuracy. Where the maximiser is unique, fitting R is itself ill-conditioned
by kappa = sigma_1 / (sigma_2 + sigma_3) (singular values of M, sigma_3 signed
by det M): a backward-stable method errs by about eps * kappa in ``|R - R*|_F``
(float32 SVD does no better). ``tests/test_methods.py`` checks
``|R - R*|_F <= 100 eps max(kappa, 1)`` against float64 SVD where the table says
"accurate"; the benchmark reports every method on every data set.

============================  ====================================  ==========================================
method                        accurate on (torchrot.testing)        fails or is inaccurate where
============================  ====================================  ==========================================
horn                          all WELL_CONDITIONED, warm_cond1e5    sigma_2 + sigma_3 = 0 (R* not unique)
mueller, converged            rot60, rot180 (kappa <~ 10)           anisotropic M: linear rate sigma_1 /
                                                                    (sigma_1 + sigma_2 + sigma_3) per step,
                                                                    so ~kappa ln(1/eps) steps are needed and
                                                                    the cap (1000) leaves ~10% (warm) to ~40%
                                                                    (warm_cond1e5) of results off by > 1e-3;
                                                                    stationary points (M = -I from I)
mueller, k steps              init close and kappa small            as above, after k steps
higham_polar                  all WELL_CONDITIONED, warm_cond1e5    singular M (NaN/Inf); with
                                                                    ``inverse="cofactor"`` in float32, det M
                                                                    of the wrong sign for kappa >~ 1e4 (2% of
                                                                    warm_cond1e5 come out 180 degrees off)
fa3r, converged               all WELL_CONDITIONED, warm_cond1e5    sigma_2 + sigma_3 = 0 (rank 1, diag(1, 1,
                                                                    -1)): the result is not a rotation
fa3r, 10 steps (authors')     rot60, rot180                         small singular values only double per
                                                                    step: condition number >~ 1e3 (warm) is
                                                                    not orthonormal after 10 steps
kugelstadt, 1 step            error O(theta^2) for init theta       large remaining rotations; the Hessian
                              from R* (warm data: most)             indefinite (guards take gradient steps)
============================  ====================================  ==========================================

One module per method (named after its paper), shared checks and helpers in
``_common`` and quaternion helpers in ``quaternions``.
"""
from __future__ import annotations

from torchrot.methods.fa3r_2018 import FA3R_CAP, FA3R_PAPER_ITERATIONS, fa3r
from torchrot.methods.higham_1986 import HIGHAM_CAP, higham_polar
from torchrot.methods.horn_1987 import horn
from torchrot.methods.kugelstadt_2018 import kugelstadt
from torchrot.methods.mueller_2016 import MUELLER_CAP, mueller
from torchrot.methods.quaternions import rotation_to_quaternion

__all__ = [
    "horn",
    "mueller",
    "higham_polar",
    "fa3r",
    "kugelstadt",
    "rotation_to_quaternion",
    "MUELLER_CAP",
    "HIGHAM_CAP",
    "FA3R_CAP",
    "FA3R_PAPER_ITERATIONS",
]
