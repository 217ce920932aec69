"""The device-generic kernel, structure of arrays: torchrot's algorithm for
accelerators (and any device), written as elementwise tensor operations. It
is the body of :func:`torchrot.fit_rotation_reference`, the kernel of the
operators on every device without a native one.

Every matrix is held as 9 separate ``(n,)`` tensors (its entries, row-major),
and every step of the C++ kernel (csrc/kernel/fit_rotation_impl.h: begin_fit /
advance / finish; cayley.h, cold_start.h, optimality.h, saddle_escape.h,
horn_fallback.h) is spelled out entry by entry, with per-matrix masks instead
of branches, so each lane executes the kernel's state machine: in float64 the
same iteration counts and status codes (tests/test_generic_path.py), but on
the rare lane where rounding decides (a degenerate maximum or a saddle): the
kernel rounds a * b + c once (csrc/kernel/mul_add.h), torch's ops twice.

Schedule (converged mode): the whole batch takes up to ``full_steps(dtype, cold)``
masked Cayley steps (most matrices converge within them), saddle escapes deferred;
the matrices still running, pending an escape or needing the fallback are
then compacted and take the rest of the kernel's step budget (escapes
included) and the Horn fallback (float64 eigh) there;
results are scattered back. Eagerly the compaction is exact (a host read) and
loops stop when no lane runs. Compiled, there is no data-dependent shape and
no graph break: the buffer has the static size ``straggler_capacity(n)``
(cumsum + scatter), lanes that do not fit take the rest on the whole batch,
masked, and the loops and the rare pieces are ``while_loop`` / ``cond`` graph
operations (see _repeat), so ``torch.compile(fullgraph=True)`` compiles the
whole algorithm as one graph (Triton kernels on CUDA, C++ on CPU) in about
two minutes on a 2-core CPU. Their predicates (whether any lane still runs)
are the only values the host reads: one flag per loop iteration (about a
dozen per call), instead of running the whole step budget on every lane.

Speed: benchmarks/generic_path.py.
"""
from __future__ import annotations

import math

import torch

from torchrot._torch_private import compile_errors
from torchrot._constants import (
    CONVERGED_CAP,
    ESTIMATE_SWITCH,
    GERSHGORIN_STEPS,
    FitStatus,
    INIT_CLEAN,
    INIT_CLEAN_STEPS,
    INIT_TOLERANCE,
    MAX_CHECK_SLACK_EPS,
    MAX_ESCAPES,
    OBJECTIVE_LAGUERRE_STEPS,
    UNDAMPED,
)

# The status codes (torchrot.FitStatus) as plain ints, which tracing takes as constants.
STATUS_CAYLEY, STATUS_FALLBACK, STATUS_BAD_INIT, STATUS_NON_FINITE = (
    int(FitStatus.CAYLEY), int(FitStatus.FALLBACK), int(FitStatus.BAD_INIT), int(FitStatus.NON_FINITE))

#: Masked Cayley steps every matrix of the batch takes before the stragglers
#: are compacted (converged mode), by compute dtype, from a warm start (see
#: full_steps); with max_iter=k <= FULL_STEPS_MAX_ITER all k steps run on the
#: whole batch. The Newton steps converge quadratically, so float64 needs one
#: more. From testing.make_warm_start (N = 1e5), float32: 7.1% of "warm"
#: lanes take 3 steps, none more; 1.6% of rot60's take 4; float64 rot60:
#: 0.004% take 5. Each whole-batch step costs the whole batch; a straggler
#: step only the buffer.
FULL_STEPS = {torch.float32: 4, torch.float64: 5}
#: The same from the cold start, both dtypes: its first step is exact (c is the
#: maximal objective) and the second confirms, so uniform and Gaussian lanes
#: take 2 steps (N = 1e5: 34 float32 uniform lanes and 15 Gaussian take 3 or
#: 4, no float64 lane more than 2); the few others finish in the buffer.
#: Measured against 4 whole-batch steps (uniform, N = 1e5, CPU, min of 9,
#: two alternations): float32 converged 771-929 -> 645 ns per matrix eagerly,
#: 201-253 -> 193-213 compiled; float64 (no third steps) unchanged.
COLD_FULL_STEPS = 2
FULL_STEPS_MAX_ITER = 8
#: Compiled, the straggler buffer holds 1/STRAGGLER_DIVISOR of the batch (at
#: least STRAGGLER_MIN lanes, at most the batch); more stragglers than that
#: take the rest of their steps on the whole batch.
STRAGGLER_DIVISOR = 8
STRAGGLER_MIN = 1024


def full_steps(dtype: torch.dtype, cold: bool) -> int:
    """Whole-batch steps before compaction for compute dtype ``dtype``, from
    the cold start (``cold``) or a warm one."""
    return COLD_FULL_STEPS if cold else FULL_STEPS[dtype]


def straggler_capacity(n: int) -> int:
    """Lanes of the compiled straggler buffer for a batch of n (integer
    arithmetic, so that a symbolic n of a dynamic-shape graph stays symbolic)."""
    return min(n, max(STRAGGLER_MIN, -(-n // STRAGGLER_DIVISOR)))


# ---------------------------------------------------------------------------
# 3x3 algebra on lists of 9 tensors
# ---------------------------------------------------------------------------


def _dot3(a0, b0, a1, b1, a2, b2):
    """a0 b0 + a1 b1 + a2 b2 in three ops (addcmul: eager makes one pass per op)."""
    return torch.addcmul(torch.addcmul(a0 * b0, a1, b1), a2, b2)


def _tmul(R, A):
    """R^T A."""
    return [_dot3(R[r], A[c], R[3 + r], A[3 + c], R[6 + r], A[6 + c]) for r in range(3) for c in range(3)]


def _mul(A, B):
    return [_dot3(A[3 * r], B[c], A[3 * r + 1], B[3 + c], A[3 * r + 2], B[6 + c]) for r in range(3) for c in range(3)]


def _dtype_name(dtype: torch.dtype) -> str:
    """"float32" for torch.float32: the key of torchrot._constants' per-dtype tables."""
    return str(dtype).removeprefix("torch.")


def _where(mask, X, Y):
    return [torch.where(mask, x, y) for x, y in zip(X, Y)]


def _gram(R):
    G = [None] * 9
    for r in range(3):
        for c in range(r, 3):
            G[3 * r + c] = R[r] * R[c] + R[3 + r] * R[3 + c] + R[6 + r] * R[6 + c]
            G[3 * c + r] = G[3 * r + c]
    return G


def _reorthonormalize(R, G=None):
    G = _gram(R) if G is None else G
    H = [(1.5 - 0.5 * g) if i % 4 == 0 else (-0.5 * g) for i, g in enumerate(G)]
    return _mul(R, H)


def _deviation2(G):
    d0, d1, d2 = G[0] - 1, G[4] - 1, G[8] - 1
    return d0 * d0 + d1 * d1 + d2 * d2 + 2 * (G[1] * G[1] + G[2] * G[2] + G[5] * G[5])


def _det(R):
    return (R[0] * (R[4] * R[8] - R[5] * R[7]) - R[1] * (R[3] * R[8] - R[5] * R[6])
            + R[2] * (R[3] * R[7] - R[4] * R[6]))


def _quaternion_rotation(w, x, y, z):
    return [
        w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z,
    ]


def _horn(M):
    """Horn's K (16 entries, row-major)."""
    t = M[0] + M[4] + M[8]
    m = [M[7] - M[5], M[2] - M[6], M[3] - M[1]]
    K = [None] * 16
    K[0] = t
    for i in range(3):
        K[1 + i] = m[i]
        K[4 * (1 + i)] = m[i]
        for j in range(3):
            s = M[3 * i + j] + M[3 * j + i]
            K[4 * (1 + i) + 1 + j] = s - t if i == j else s
    return K


# ---------------------------------------------------------------------------
# The kernel's pieces
# ---------------------------------------------------------------------------


def _objective_estimate(S, t, mm, variant):
    if variant == "newton":
        return t
    g = t
    if variant == "gershgorin":
        s01 = (S[1] + S[3]).abs()
        s02 = (S[2] + S[6]).abs()
        s12 = (S[5] + S[7]).abs()
        two_l2 = torch.maximum(2 * S[0] + s01 + s02, torch.maximum(2 * S[4] + s01 + s12, 2 * S[8] + s02 + s12))
        g = torch.maximum(t, two_l2 - t)
    return torch.sqrt(g * g + mm)


def _cayley_step(S, t, m, c):
    """Algorithm 2 (cayley_step, cayley.h): w = adj(H) m, d = det H, w.w, d^2 and
    |H|_F^2 for H = S + S^T - (t + c) I."""
    shift = t + c
    h00, h11, h22 = 2 * S[0] - shift, 2 * S[4] - shift, 2 * S[8] - shift
    h01, h02, h12 = S[1] + S[3], S[2] + S[6], S[5] + S[7]
    c00 = h11 * h22 - h12 * h12
    c01 = h02 * h12 - h01 * h22
    c02 = h01 * h12 - h02 * h11
    c11 = h00 * h22 - h02 * h02
    c12 = h01 * h02 - h00 * h12
    c22 = h00 * h11 - h01 * h01
    d = h00 * c00 + h01 * c01 + h02 * c02
    w0 = c00 * m[0] + c01 * m[1] + c02 * m[2]
    w1 = c01 * m[0] + c11 * m[1] + c12 * m[2]
    w2 = c02 * m[0] + c12 * m[1] + c22 * m[2]
    hh = h00 * h00 + h11 * h11 + h22 * h22 + 2 * (h01 * h01 + h02 * h02 + h12 * h12)
    return (w0, w1, w2), d, w0 * w0 + w1 * w1 + w2 * w2, d * d, hh


def _cayley_rotation(w, d, ww, dd):
    x, y, z = w
    inv = 1 / (dd + ww)
    diag = dd - ww
    two_inv = 2 * inv
    two_d_inv = d * two_inv
    xy, xz, yz = x * y * two_inv, x * z * two_inv, y * z * two_inv
    dx, dy, dz = x * two_d_inv, y * two_d_inv, z * two_d_inv
    return [
        (diag + 2 * x * x) * inv, xy + dz, xz - dy,
        xy - dz, (diag + 2 * y * y) * inv, yz + dx,
        xz + dy, yz - dx, (diag + 2 * z * z) * inv,
    ]


def _is_maximum(S, slack):
    """is_maximum (optimality.h): P = tr(S) I - sym(S) + slack I positive definite, by
    elimination on P's largest diagonal entry and the 2x2 Schur complement."""
    t = S[0] + S[4] + S[8] + slack
    p00, p11, p22 = t - S[0], t - S[4], t - S[8]
    p01, p02, p12 = -0.5 * (S[1] + S[3]), -0.5 * (S[2] + S[6]), -0.5 * (S[5] + S[7])
    pivot0 = ~(p00 < p11) & ~(p00 < p22)
    pivot1 = ~pivot0 & ~(p11 < p22)

    def pick(if0, if1, if2):
        return torch.where(pivot0, if0, torch.where(pivot1, if1, if2))

    pivot = pick(p00, p11, p22)
    paa, pbb, pab = pick(p11, p00, p00), pick(p22, p22, p11), pick(p12, p02, p01)
    pai, pbi = pick(p01, p01, p02), pick(p02, p12, p12)
    qaa = paa * pivot - pai * pai  # the Schur complement times the pivot
    qbb = pbb * pivot - pbi * pbi
    qab = pab * pivot - pai * pbi
    return (pivot > 0) & (qaa > 0) & (qaa * qbb - qab * qab > 0)


def _saddle_escape_rotation(S, squarings=4):
    B = [0.5 * (S[3 * r + c] + S[3 * c + r]) for r in range(3) for c in range(3)]
    lower = B[0]
    for r in range(3):
        radius = sum(B[3 * r + c].abs() for c in range(3) if c != r)
        bound = B[4 * r] - radius
        lower = torch.where(bound < lower, bound, lower)
    B = [b - lower if i % 4 == 0 else b for i, b in enumerate(B)]
    for _ in range(squarings):
        inv_trace = 1 / (B[0] + B[4] + B[8])
        B = [b * inv_trace for b in B]
        B = _mul(B, B)
    v = [B[0], B[3], B[6]]
    vv = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    for c in (1, 2):
        norm = B[c] * B[c] + B[3 + c] * B[3 + c] + B[6 + c] * B[6 + c]
        larger = norm > vv
        v = [torch.where(larger, B[3 * r + c], v[r]) for r in range(3)]
        vv = torch.where(larger, norm, vv)
    k = 2 / vv
    return [k * v[r] * v[c] - (1 if r == c else 0) for r in range(3) for c in range(3)]


#: cold_start.h's kStartPerm: row i's entry of permutation p is in column
#: _START_PERMS[p][i]; the first three are even.
_START_PERMS = ((0, 1, 2), (1, 2, 0), (2, 0, 1), (0, 2, 1), (2, 1, 0), (1, 0, 2))


def _best_start_rotation(A):
    """The best of the 24 rotations of the cube (signed permutation matrices
    of det +1) for tr(P^T A), the first of equals (cold_start.h, step by
    step: each permutation with the signs of its entries, the smallest one
    flipped where det would be -1; the winner's entries and columns kept),
    and its objective."""
    best = odd_perm = None
    entry, column = [None] * 3, [None] * 3
    for p, col in enumerate(_START_PERMS):
        xyz = (A[col[0]], A[3 + col[1]], A[6 + col[2]])
        a, b, c = (v.abs() for v in xyz)
        product = (xyz[0] * xyz[1]) * xyz[2]
        flip = product < 0 if p < 3 else product > 0
        total = (a + b) + c
        value = torch.where(flip, total - 2 * torch.minimum(torch.minimum(a, b), c), total)
        if p == 0:
            best, odd_perm = value, torch.zeros_like(flip)
            entry = list(xyz)
            column = [torch.full(value.shape, col[i], dtype=_INT, device=value.device) for i in range(3)]
            continue
        better = value > best  # strict: the first of equals wins, as in the kernel
        best = torch.where(better, value, best)
        odd_perm = torch.where(better, p >= 3, odd_perm)
        entry = [torch.where(better, xyz[i], entry[i]) for i in range(3)]
        column = [torch.where(better, col[i], column[i]) for i in range(3)]
    size = [e.abs() for e in entry]
    flip = odd_perm ^ (entry[0] < 0) ^ (entry[1] < 0) ^ (entry[2] < 0)
    smallest0 = ~(size[0] > size[1]) & ~(size[0] > size[2])
    smallest1 = ~smallest0 & ~(size[1] > size[2])
    smallest = (smallest0, smallest1, ~(smallest0 | smallest1))
    R = []
    for i in range(3):
        sign = torch.where(entry[i] < 0, -1.0, 1.0).to(A[0].dtype)
        s = torch.where(flip & smallest[i], -sign, sign)
        R += [torch.where(column[i] == j, s, 0.0).to(A[0].dtype) for j in range(3)]
    return R, best


def _maximal_objective(A, lower):
    """max_R tr(R^T A), K's largest eigenvalue, by Laguerre's method on K's
    characteristic polynomial from above (maximal_objective.h, step by step,
    with kernel::Tolerances' sqrt(eps) and step cap); ``lower``: an attained
    objective (the cube start's)."""
    tol = UNDAMPED[_dtype_name(A[0].dtype)]
    t = A[0] + A[4] + A[8]
    m = (A[7] - A[5], A[2] - A[6], A[3] - A[1])
    w, d, _, _, _ = _cayley_step(A, t, m, 0)  # T = A + A^T - t I is Algorithm 2's H for c = 0
    p0 = t * d - (m[0] * w[0] + m[1] * w[1] + m[2] * w[2])  # det K
    norm2 = sum(a * a for a in A)
    p2, p1 = -2 * norm2, -8 * _det(A)
    x = torch.sqrt(3 * norm2)
    active = x > 0
    for _ in range(OBJECTIVE_LAGUERRE_STEPS):
        if not _compiling() and not _any(active):
            break
        x2 = x * x
        p = ((x2 + p2) * x + p1) * x + p0
        dp = (4 * x2 + 2 * p2) * x + p1
        ddp = 12 * x2 + 2 * p2
        root = torch.sqrt(torch.clamp(9 * dp * dp - 12 * (p * ddp), min=0))
        nxt = x - 4 * p / (dp + root)
        move = active & (nxt < x) & ~(nxt < lower)
        active = move & (x - nxt > tol * nxt)
        x = torch.where(move, nxt, x)
    return x


def _horn_rotation(A):
    """The guaranteed fallback (horn_fallback.h): Horn's quaternion method in
    float64, the top eigenvector of K by torch.linalg.eigh (an extern kernel:
    the kernel's unrolled Jacobi sweeps would be a pointwise chain too deep
    for inductor to compile)."""
    device = A[0].device
    if device.type == "mps":  # no float64 and no eigh there: the (rare) fallback lanes go to the CPU
        A = [a.cpu() for a in A]
    K = torch.stack(_horn([a.double() for a in A]), -1).reshape(-1, 4, 4)
    q = torch.linalg.eigh(K).eigenvectors[..., 3]  # eigenvalues ascending: the largest is last
    R = _quaternion_rotation(q[:, 0], q[:, 1], q[:, 2], q[:, 3])
    return [r.to(device=device, dtype=A[0].dtype) for r in R]


# ---------------------------------------------------------------------------
# Control flow: data-dependent, without host synchronisation when compiled
# ---------------------------------------------------------------------------
#
# Eager, the loops stop as soon as no lane runs and the rare pieces (saddle
# escapes, the Horn fallback, the overflow pass) run only when some lane needs
# them: one host read of a mask each (free on CPU). Compiled, the same
# decisions are graph operations (torch.while_loop,
# torch.cond), traced once each: no graph break, no unrolling (the graph stays
# small enough to compile in about two minutes). Both spellings take the same
# decisions, so results do not depend on the mode.


def _compiling() -> bool:
    return torch.compiler.is_compiling()


def _any(mask: torch.Tensor) -> bool:
    """Eager only: whether some lane of ``mask`` is set (``meta``: assume so)."""
    return mask.device.type == "meta" or bool(mask.any())


def _masked_update(mask, fn, R, operands):
    """R (9 tensors) with the lanes of ``mask`` replaced by ``fn(*operands)``,
    which is computed only when some lane is set."""
    if not _compiling():  # only the lanes of mask, gathered
        if mask.device.type == "meta":
            return _where(mask, fn(*operands), R)
        idx = mask.nonzero().squeeze(1)
        if idx.numel() == 0:
            return R
        return [r.index_put((idx,), v) for r, v in zip(R, fn(*(x[idx] for x in operands)))]
    k = len(R)

    def replace(mask, *xs):
        return tuple(_where(mask, fn(*xs[k:]), list(xs[:k])))

    def keep(mask, *xs):
        return tuple(x.clone() for x in xs[:k])

    return list(torch.cond(mask.any(), replace, keep, (mask, *R, *operands)))


_LANE_KEYS = ("running", "fallback", "switched", "iterations", "attempt", "escapes", "pending")


#: Compiled, loops of at most this many steps are unrolled (the one-step warm start).
UNROLL_MAX_STEPS = 2


def _repeat(step, st, steps, unroll=True):
    """Up to ``steps`` applications of ``step`` to the lane state ``st``
    (a dict: ``A``, ``R`` and _LANE_KEYS), stopping once no lane runs.
    Compiled, ``unroll`` lets a loop of at most UNROLL_MAX_STEPS steps be
    unrolled; otherwise it is a while_loop."""
    if steps <= 0:
        return st
    if not _compiling():
        for _ in range(steps):
            if not _any(st["running"]):
                break
            st = step(st)
        return st
    if unroll and steps <= UNROLL_MAX_STEPS:  # a short fixed loop fuses into one kernel (finished lanes' steps are no-ops)
        for _ in range(steps):
            st = step(st)
        return st
    A = st["A"]
    # The lane flags travel through the loop as int32 0/1: inductor's CPU code
    # loads and stores bool buffers byte by byte (a branch per lane), which
    # made a step about 4x slower; int32 lanes load and store as vectors.
    flags = {k for k in _LANE_KEYS if st[k].dtype == torch.bool}
    pack = lambda s: (*s["R"], *(s[k].to(_INT) if k in flags else s[k] for k in _LANE_KEYS))

    def unpack(xs):
        lanes = {k: (x != 0 if k in flags else x) for k, x in zip(_LANE_KEYS, xs[9:])}
        return {"A": A, "R": list(xs[:9]), **lanes}

    def cond(i, *xs):
        return (i < steps) & (xs[9] != 0).any()  # xs[9]: running

    def body(i, *xs):
        out = pack(step(unpack(xs)))
        return (i + 1, *(o.clone() if any(o is x for x in xs) else o for o in out))

    carried = []
    for x in pack(st):  # while_loop rejects carried inputs that alias each other
        carried.append(x.clone() if any(x is y for y in carried) else x)
    counter = torch.zeros((), dtype=torch.int64, device=A[0].device)
    return unpack(torch.while_loop(cond, body, (counter, *carried))[1:])


# ---------------------------------------------------------------------------
# The state machine
# ---------------------------------------------------------------------------

_INT = torch.int32


def _step(st, variant, converge, cap, eps, objective=None):
    """One masked Cayley step of the kernel's advance() on the lane state
    (with c = ``objective`` if given: the first step from the cold start).

    A lane that stops at a saddle point (converged mode) with escapes left is
    marked ``pending`` and stops running; _apply_pending_escapes applies the
    escape and restarts it, as the kernel does within the same step."""
    A, R = st["A"], st["R"]
    running, fallback, switched = st["running"], st["fallback"], st["switched"]
    iterations, attempt, escapes = st["iterations"], st["attempt"], st["escapes"]
    tiny = torch.finfo(A[0].dtype).tiny
    undamped_tol = UNDAMPED[_dtype_name(A[0].dtype)]
    S = _tmul(R, A)
    t = S[0] + S[4] + S[8]
    m = (S[7] - S[5], S[2] - S[6], S[3] - S[1])
    mm = m[0] * m[0] + m[1] * m[1] + m[2] * m[2]
    if objective is not None:
        c = objective
    else:
        c = _objective_estimate(S, t, mm, variant)
        if converge and variant == "gershgorin":
            c = torch.where(switched, _objective_estimate(S, t, mm, "conservative"), c)
    w, d, ww, dd, hh = _cayley_step(S, t, m, c)
    norm2 = dd + ww
    valid = (dd > 0) & torch.isfinite(norm2) & (norm2 > tiny)
    stepping = running & valid
    stalled = running & ~valid
    safe_d = torch.where(stepping, d, 1.0)
    safe_dd = torch.where(stepping, dd, 1.0)
    safe_w = [torch.where(stepping, x, 0.0) for x in w]
    # Lanes not stepping get Q = I exactly (w = 0, d = 1): R Q = R, no select needed.
    Q = _cayley_rotation(safe_w, safe_d, torch.where(stepping, ww, 0.0), safe_dd)
    R = _mul(R, Q)
    step_i = stepping.to(_INT)
    iterations = iterations + step_i
    attempt = attempt + step_i
    undamped = ~(c - t > undamped_tol * t.abs())
    finished = stepping & undamped & (ww < eps * dd)
    pending = st["pending"]
    if converge:
        singular = finished & ~(mm < eps * hh)  # CayleyStep::singular (cayley.h)
        stalled = stalled | singular
        finished = finished & ~singular
        switch_now = (ww < ESTIMATE_SWITCH * dd) | (attempt >= GERSHGORIN_STEPS)
        switched = switched | (stepping & switch_now)
        saddle = finished & ~_is_maximum(S, MAX_CHECK_SLACK_EPS * eps)
        escape = saddle & (escapes < MAX_ESCAPES)
        fallback = fallback | (saddle & ~escape)
        pending = pending | escape
        exhausted = stepping & ~finished & (attempt >= cap)
        fallback = fallback | exhausted | stalled
        finished = finished | exhausted | stalled
    else:
        finished = finished | stalled | (attempt >= cap)
    return dict(st, R=R, running=running & ~finished, fallback=fallback, switched=switched,
                iterations=iterations, attempt=attempt, pending=pending)


def _apply_pending_escapes(st):
    """The saddle escape (saddle_escape.h) of the pending lanes, which then run again."""
    pending = st["pending"]
    if not _compiling() and not _any(pending):
        return st
    R = _masked_update(pending, lambda *RA: _mul(list(RA[:9]), _saddle_escape_rotation(_tmul(list(RA[:9]), list(RA[9:])))),
                       st["R"], (*st["R"], *st["A"]))
    return dict(st, R=R, running=st["running"] | pending, pending=pending & False,
                escapes=st["escapes"] + pending.to(_INT), attempt=torch.where(pending, 0, st["attempt"]),
                switched=st["switched"] & ~pending)


def _advance_and_finish(st, steps, variant, converge, cap, eps):
    """Pending escapes, up to ``steps`` more Cayley steps on the lanes of
    ``st``, then finish(): the Newton-Schulz clean-up and, in converged mode,
    the Horn fallback. Returns (R, final state)."""
    st = _apply_pending_escapes(st)
    st = _repeat(lambda s: _apply_pending_escapes(_step(s, variant, converge, cap, eps)), st, steps)
    R = _reorthonormalize(st["R"])
    if converge:
        R = _masked_update(st["fallback"], lambda *A: _horn_rotation(list(A)), R, st["A"])
    return R, st


def _compact_indices(sel, capacity):
    """Indices (capacity,) of the first `capacity` set lanes of `sel`, padded
    with n (no host sync), the valid mask, and the lanes that did not fit."""
    n = sel.shape[0]
    pos = torch.cumsum(sel.to(torch.int64), 0) - 1
    take = sel & (pos < capacity)
    dest = torch.where(take, pos, capacity)
    idx = torch.full((capacity + 1,), n, dtype=torch.int64, device=sel.device)
    idx = idx.scatter(0, dest, torch.arange(n, device=sel.device))[:capacity]
    return idx, idx < n, sel & ~take


def _gather(x, idx, n):
    return x.index_select(0, idx.clamp(max=n - 1))


def _scatter_back(x, sub, idx, valid):
    n = x.shape[0]
    dest = torch.where(valid, idx, n)
    full = torch.cat([x, x[:1]])
    return full.scatter(0, dest, sub)[:n]


def _masked_lanes(st, mask):
    """``st`` restricted to the lanes of ``mask`` (the others neither run nor fall back)."""
    return dict(st, running=st["running"] & mask, fallback=st["fallback"] & mask, pending=st["pending"] & mask)


def fit_soa(A, R, running, variant, max_iter, eps, objective=None):
    """Runs advance + finish on SoA state; returns (R list, iterations, fallback).
    ``objective``: the first step's estimate c (cold starts: the maximal objective).

    Schedule: every lane takes up to full_steps(dtype, cold) steps on the whole batch
    (saddle escapes deferred); the lanes still running, falling back or
    pending an escape are then compacted into a buffer of
    straggler_capacity(n) lanes that takes the rest of the step budget and
    the fallback; lanes that did not fit (more stragglers than the buffer
    holds: rare) take it on the whole batch, masked. Each lane executes the
    kernel's state machine, so results do not depend on the tiering."""
    n = running.shape[0]
    converge = max_iter is None
    cap = CONVERGED_CAP if converge else max_iter
    budget = CONVERGED_CAP * (MAX_ESCAPES + 1) if converge else max_iter
    zeros_b = torch.zeros_like(running)
    zeros_i = torch.zeros(running.shape, dtype=_INT, device=running.device)
    # After an exact first step (cold starts) the Gershgorin variant goes on with the conservative estimate.
    cold = objective is not None
    st = {"A": A, "R": R, "running": running, "fallback": zeros_b,
          "switched": ~zeros_b if cold else zeros_b,
          "iterations": zeros_i, "attempt": zeros_i, "escapes": zeros_i, "pending": zeros_b}
    full = budget if (not converge and max_iter <= FULL_STEPS_MAX_ITER) else min(full_steps(A[0].dtype, cold), budget)
    # A lane pending an escape after step k <= full needs at most
    # MAX_ESCAPES * CONVERGED_CAP more steps (<= budget - full).
    if cold:  # every lane's first step (full >= 1)
        st = _step(st, variant, converge, cap, eps, objective)
    # Compiled, steps unrolled after the exact first step fuse with it and
    # made the fit slower (measured, float32 uniform, N = 1e5, CPU: converged
    # 241 -> 311 ns per matrix with one step unrolled, 540 with two), so
    # there they stay a while_loop.
    st = _repeat(lambda s: _step(s, variant, converge, cap, eps), st, full - 1 if cold else full,
                 unroll=not cold)
    rest = budget - full
    capacity = straggler_capacity(n) if n > 0 else 0
    R = _reorthonormalize(st["R"])
    if capacity == 0 or (rest == 0 and not converge):
        return R, st["iterations"], st["fallback"]
    sel = st["running"] | st["fallback"] | st["pending"]
    if not _compiling():
        # Eager: host reads are allowed, so the stragglers are compacted exactly.
        if not _any(sel):
            return R, st["iterations"], st["fallback"]
        if sel.device.type != "meta":
            idx = sel.nonzero().squeeze(1)
            sub = {"A": [a[idx] for a in st["A"]], "R": [r[idx] for r in st["R"]], **{k: st[k][idx] for k in _LANE_KEYS}}
            R_sub, sub = _advance_and_finish(sub, rest, variant, converge, cap, eps)
            put = lambda x, y: x.index_put((idx,), y)
            return [put(r, rs) for r, rs in zip(R, R_sub)], put(st["iterations"], sub["iterations"]), put(st["fallback"], sub["fallback"])
    idx, valid, overflow = _compact_indices(sel, capacity)
    sub = {"A": [_gather(a, idx, n) for a in st["A"]], "R": [_gather(r, idx, n) for r in st["R"]]}
    for k in _LANE_KEYS:
        sub[k] = _gather(st[k], idx, n)
    R_sub, sub = _advance_and_finish(_masked_lanes(sub, valid), rest, variant, converge, cap, eps)
    R = [_scatter_back(r, rs, idx, valid) for r, rs in zip(R, R_sub)]
    iterations = _scatter_back(st["iterations"], sub["iterations"], idx, valid)
    fallback = _scatter_back(st["fallback"], sub["fallback"], idx, valid)
    if _compiling() or _any(overflow):
        # The lanes that did not fit, on the whole batch, masked (eager:
        # only when there are such lanes; compiled: its loop stops at once).
        R_ov, ov = _advance_and_finish(_masked_lanes(st, overflow), rest, variant, converge, cap, eps)
        R = _where(overflow, R_ov, R)
        iterations = torch.where(overflow, ov["iterations"], iterations)
        fallback = torch.where(overflow, ov["fallback"], fallback)
    return R, iterations, fallback


def _components(X, n):
    """(..., 3, 3) -> 9 contiguous (n,) tensors."""
    flat = X.reshape(n, 9).t().contiguous()
    if _compiling() and X.device.type == "cpu" and X.dtype == torch.float32:
        # Inductor must store an as_strided view's input: the transposed
        # entries are written once (a tiled, vectorised transpose) and the
        # kernels that read them load contiguous vectors. Inlined instead,
        # each read is a stride-9 load of X, and inductor's CPU code then runs
        # the whole consuming kernel (normalisation and cold start) one lane at
        # a time: ~70 ns per matrix instead of ~40 (benchmarks/generic_path.py).
        # Not in float64: there inductor's vector code (two AVX2 registers per
        # value) ran slower than its scalar loop (one-step fit 387 vs 133 ns).
        # Not on accelerators: nothing measured there.
        flat = flat.as_strided((9, n), (n, 1))
    return list(flat.unbind(0))


def _normalized(M):
    """M / max|M| entrywise, subnormal-scaled matrices lifted by 2^(digits+1)
    first (as the kernel): (A, max_abs, zero, lift, inv) with A = (M lift) inv."""
    max_abs = M[0].abs()
    for x in M[1:]:
        max_abs = torch.maximum(max_abs, x.abs())  # NaN propagates
    finfo = torch.finfo(M[0].dtype)
    digits = round(-math.log2(finfo.eps)) + 1
    lift = torch.where(max_abs < finfo.tiny, torch.full_like(max_abs, float(2**digits)), torch.ones_like(max_abs))
    zero = max_abs == 0
    inv = torch.where(zero, 0.0, 1 / torch.where(zero, 1.0, max_abs * lift))
    return [(x * lift) * inv for x in M], max_abs, zero, lift, inv


def _warm_start_components(init, compute):
    """init's 9 components in ``compute``, in init's batch shape, with its
    Gram matrix, finiteness, rejection (check_warm_start, optimality.h) and
    squared deviation from orthonormality."""
    batch = init.shape[:-2]
    I = [x.reshape(batch) for x in _components(init.to(compute), math.prod(batch))]
    G = _gram(I)
    finite = torch.isfinite(G[0] + G[4] + G[8])
    dev2 = _deviation2(G)
    bad = finite & ~((dev2 < INIT_TOLERANCE**2) & (_det(I) > 0))
    return I, G, finite, bad, dev2


def _compute_dtype(dtype):
    return torch.float32 if dtype in (torch.float16, torch.bfloat16) else dtype


def _fit_core(M, init, max_iter, variant, warm=None):
    """(R, iterations, status) for M: the whole algorithm as tensor operations
    (no host read when compiled; see _repeat). ``warm``: init's
    _warm_start_components if the caller has them already."""
    compute = _compute_dtype(M.dtype)
    shape = M.shape
    batch = shape[:-2]
    n = math.prod(batch)
    eps = torch.finfo(compute).eps
    A, max_abs, zero, _, _ = _normalized(_components(M.to(compute), n))
    finite = torch.isfinite(max_abs)
    bad_init = torch.zeros_like(finite)
    objective = None  # the first step's estimate c: cold starts only
    if init is not None:
        I, G, init_finite, init_bad, dev2 = warm if warm is not None else _warm_start_components(init, compute)
        ex = lambda t: t.expand(batch).reshape(n)
        init_finite, init_bad, dev2 = ex(init_finite), ex(init_bad), ex(dev2)
        R, G = [ex(x) for x in I], [ex(g) for g in G]
        finite = finite & init_finite
        bad_init = init_bad
        # clean_warm_start: masked Newton-Schulz steps for lanes above the
        # dtype's clean threshold (eager: only while some lane needs one).
        clean2 = INIT_CLEAN[_dtype_name(compute)] ** 2
        rough = init_finite & ~init_bad & ~(dev2 < clean2)
        for _ in range(INIT_CLEAN_STEPS):
            if not _compiling() and not _any(rough):
                break
            R = _where(rough, _reorthonormalize(R, G), R)
            G = _gram(R)
            rough = rough & ~(_deviation2(G) < clean2)
    else:
        R, start_objective = _best_start_rotation(A)
        objective = _maximal_objective(A, start_objective)
    A = _where(finite, A, [torch.zeros_like(a) for a in A])  # NaN stays in its lane
    running = finite & ~zero & ~bad_init
    R, iterations, fallback = fit_soa(A, R, running, variant, max_iter, eps, objective)
    nan_lane = ~finite | bad_init
    R = [torch.where(nan_lane, float("nan"), r) for r in R]
    out = torch.stack(R, -1).reshape(shape).to(M.dtype)
    status = torch.where(fallback, STATUS_FALLBACK, STATUS_CAYLEY)
    status = torch.where(bad_init, STATUS_BAD_INIT, status)
    status = torch.where(finite, status, STATUS_NON_FINITE).to(torch.uint8)
    return out, iterations.reshape(batch), status.reshape(batch)


#: Device types whose tensors run the algorithm compiled
#: (torch.compile(fullgraph=True): fused kernels, no host read); others, and
#: these when compilation fails (e.g. no Triton), run it eagerly.
COMPILED_DEVICE_TYPES = frozenset({"cuda", "xpu"})
_compiled_cores: dict = {}


def _core_for(device: torch.device):
    if device.type not in COMPILED_DEVICE_TYPES or _compiling():
        return _fit_core
    if device.type not in _compiled_cores:
        _compiled_cores[device.type] = torch.compile(_fit_core, fullgraph=True)
    return _compiled_cores[device.type]


def _run_core(M, init, max_iter, variant, warm=None):
    """_fit_core, compiled on COMPILED_DEVICE_TYPES; ``warm`` serves the eager
    core only (the compiled graph computes its own from init)."""
    core = _core_for(M.device)
    if core is _fit_core:
        return core(M, init, max_iter, variant, warm)
    try:
        return core(M, init, max_iter, variant)
    except compile_errors() as error:  # e.g. no Triton for this device: run eagerly from now on
        import warnings

        warnings.warn(f"torchrot: torch.compile failed on {M.device.type} tensors ({type(error).__name__}: "
                      f"{error}); the device-generic path runs eagerly", RuntimeWarning, stacklevel=3)
        _compiled_cores[M.device.type] = _fit_core
        return _fit_core(M, init, max_iter, variant, warm)


def fit_rotation_generic(M, init, max_iter, variant, return_info, bad_init_error):
    """The body of fit_rotation_reference (arguments already checked): raises
    ``bad_init_error(count, total)`` for a finite warm start that is not a
    rotation (eager, before anything else; not on ``meta`` tensors nor while
    traced, where such lanes come back NaN with status STATUS_BAD_INIT)."""
    warm = None
    if init is not None and M.device.type != "meta" and not _compiling():
        warm = _warm_start_components(init, _compute_dtype(M.dtype))
        init_bad = warm[3]
        if bool(init_bad.any()):
            raise bad_init_error(int(init_bad.sum()), init_bad.numel())  # counted in init's own shape
    R, iterations, status = _run_core(M, init, max_iter, variant, warm)
    return (R, iterations, status) if return_info else R


def rotation_tangent(X, R, M, damping):
    """csrc/kernel/rotation_gradient.h's rotation_tangent on SoA lists:
    R [u]x with u = Re (K + i lambda I)^-1 g (no K^2: float32 keeps its digits)."""
    dtype = R[0].dtype
    finfo = torch.finfo(dtype)
    A, max_abs, zero, lift, inv_max = _normalized(M)
    frob2 = sum(a * a for a in A)
    frob = torch.where(zero, 1.0, torch.sqrt(frob2))
    S = _tmul(R, A)
    inv_frob = 1 / frob
    trace = (S[0] + S[4] + S[8]) * inv_frob
    half_inv = 0.5 * inv_frob
    k00, k11, k22 = trace - S[0] * inv_frob, trace - S[4] * inv_frob, trace - S[8] * inv_frob
    k01, k02, k12 = -(S[1] + S[3]) * half_inv, -(S[2] + S[6]) * half_inv, -(S[5] + S[7]) * half_inv
    x_max = X[0].abs()
    for x in X[1:]:
        x_max = torch.maximum(x_max, x.abs())
    half_range = (int(math.log2(finfo.max)) + 1) // 2  # max_exponent / 2
    x_huge = x_max > 2.0**half_range
    x_down = torch.where(x_huge, torch.full_like(x_max, 2.0**-half_range), torch.ones_like(x_max))
    Xs = [x * x_down for x in X]
    B = _tmul(R, Xs)
    g = (B[7] - B[5], B[2] - B[6], B[3] - B[1])
    c00, c01, c02 = k11 * k22 - k12 * k12, k02 * k12 - k01 * k22, k01 * k12 - k02 * k11
    c11, c12, c22 = k00 * k22 - k02 * k02, k01 * k02 - k00 * k12, k00 * k11 - k01 * k01
    det_k = k00 * c00 + k01 * c01 + k02 * c02
    trace_k = k00 + k11 + k22
    lam, lam2 = float(damping), float(damping) * float(damping)
    a = det_k - lam2 * trace_k
    b = lam * (c00 + c11 + c22 - lam2)
    adj_g = (c00 * g[0] + c01 * g[1] + c02 * g[2], c01 * g[0] + c11 * g[1] + c12 * g[2],
             c02 * g[0] + c12 * g[1] + c22 * g[2])
    shift_g = (trace_k * g[0] - (k00 * g[0] + k01 * g[1] + k02 * g[2]),
               trace_k * g[1] - (k01 * g[0] + k11 * g[1] + k12 * g[2]),
               trace_k * g[2] - (k02 * g[0] + k12 * g[1] + k22 * g[2]))
    ab_max = torch.maximum(a.abs(), b.abs())
    solvable = ab_max > finfo.tiny
    inv_ab = torch.where(solvable, 1 / torch.where(solvable, ab_max, 1.0), 0.0)
    as_, bs = a * inv_ab, b * inv_ab
    norm2 = torch.where(solvable, as_ * as_ + bs * bs, 1.0)
    w_adj = as_ * inv_ab / norm2
    w_shift = bs * inv_ab / norm2 * lam
    huge = finfo.max
    sat = lambda v: v.clamp(-huge, huge)
    u = [sat(sat(w_adj * (adj_g[i] - lam2 * g[i])) + sat(w_shift * shift_g[i])) for i in range(3)]
    scale = torch.clamp(lift * inv_max * inv_frob, max=huge)
    x_up = torch.where(x_huge, torch.full_like(x_max, 2.0**half_range), torch.ones_like(x_max))
    T = []
    for r in range(3):
        R0, R1, R2 = R[3 * r], R[3 * r + 1], R[3 * r + 2]
        T += [R1 * u[2] - R2 * u[1], R2 * u[0] - R0 * u[2], R0 * u[1] - R1 * u[0]]
    return [sat(sat(t * scale) * x_up) for t in T]


def fit_rotation_backward_generic(grad, R, M, gradient_eps):
    """The body of fit_rotation_backward_reference (arguments already checked)."""
    out_dtype = R.dtype
    compute = _compute_dtype(R.dtype)
    shape = R.shape
    n = math.prod(shape[:-2])
    Gc = _components(grad.to(compute), n)
    Rc = _components(R.to(compute), n)
    Mc = _components(M.to(compute).expand(shape), n)
    T = rotation_tangent(Gc, Rc, Mc, gradient_eps)
    return torch.stack(T, -1).reshape(shape).to(out_dtype)
