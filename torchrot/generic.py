"""The device-generic kernel, structure of arrays: torchrot's algorithm for
accelerators (and any device), written as elementwise tensor operations.

Every matrix is held as 9 separate ``(n,)`` tensors (its entries, row-major),
and every step of the C++ kernel (csrc/kernel/fit_rotation_impl.h: begin_fit /
advance / finish; cayley.h, cold_start.h, optimality.h, saddle_escape.h,
horn_fallback.h) is spelled out entry by entry, with per-matrix masks instead
of branches. No host synchronisation (no ``.item()``, no ``bool(tensor)``, no
data-dependent shapes), so ``torch.compile(fullgraph=True)`` fuses it into a
few loops (Triton kernels on CUDA, C++ on CPU).

Schedule (converged mode): the whole batch takes ``FULL_STEPS`` masked Cayley
steps (most matrices converge within them, see benchmarks/generic_path.py);
then the matrices still running or needing the fallback are compacted, without
a host sync (cumsum + scatter into a buffer of static size
``straggler_capacity(n)``), and take the rest of the kernel's step budget
(saddle escapes included) and the Horn fallback (fixed Jacobi sweeps in
float64) there; results are scattered back. Each lane executes exactly the
kernel's state machine, so results, iteration counts and status codes do not
depend on the tiering (as in the kernel, which regroups slow lanes too).

Status (work in progress, not yet behind fit_rotation_reference's forward;
its backward, rotation_tangent, is): matches the C++ kernel's iteration
counts and status codes in float64 and meets testing.CRITERIA on every
distribution and edge case (tests/test_generic_path.py). Not yet fast:
- lanes that do not fit in the straggler buffer (more than
  straggler_capacity(n) matrices needing more than FULL_STEPS steps, e.g. a
  batch of rank-1 matrices) are completed by a whole-batch masked pass
  (``_COMPLETE_OVERFLOW``, on by default: correctness first). Without a host
  sync it cannot be skipped, so it is always paid (~4x the eager cost);
- the converged graph (36 unrolled steps, two unrolled Jacobi fallbacks) takes
  inductor more than 10 minutes to compile; max_iter <= 8 compiles in ~1 min.
"""
from __future__ import annotations

import math

import torch

from torchrot._limits import (
    CONVERGED_CAP,
    ESTIMATE_SWITCH,
    GERSHGORIN_STEPS,
    INIT_CLEAN,
    INIT_CLEAN_STEPS,
    INIT_TOLERANCE,
    MAX_CHECK_SLACK_EPS,
    MAX_ESCAPES,
)

STATUS_CAYLEY, STATUS_FALLBACK, STATUS_BAD_INIT, STATUS_NON_FINITE = 0, 1, 2, 3

#: Masked Cayley steps every matrix of the batch takes before the stragglers
#: are compacted (converged mode; with max_iter=k <= FULL_STEPS_MAX_ITER all k
#: steps run on the whole batch).
FULL_STEPS = 6
FULL_STEPS_MAX_ITER = 8
#: Jacobi sweeps of the fallback (4x4, cyclic: quadratic convergence).
JACOBI_SWEEPS = 6
#: Fraction of the batch the compacted straggler buffer holds (at least
#: STRAGGLER_MIN lanes, at most the batch).
STRAGGLER_FRACTION = 0.125
STRAGGLER_MIN = 1024


def straggler_capacity(n: int) -> int:
    return min(n, max(STRAGGLER_MIN, int(math.ceil(n * STRAGGLER_FRACTION))))


# ---------------------------------------------------------------------------
# 3x3 algebra on lists of 9 tensors
# ---------------------------------------------------------------------------


def _tmul(R, A):
    """R^T A."""
    return [R[r] * A[c] + R[3 + r] * A[3 + c] + R[6 + r] * A[6 + c] for r in range(3) for c in range(3)]


def _mul(A, B):
    return [A[3 * r] * B[c] + A[3 * r + 1] * B[3 + c] + A[3 * r + 2] * B[6 + c] for r in range(3) for c in range(3)]


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
    return (w0, w1, w2), d, w0 * w0 + w1 * w1 + w2 * w2, d * d


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
    t = S[0] + S[4] + S[8] + slack
    p00, p11, p22 = t - S[0], t - S[4], t - S[8]
    p01, p02, p12 = -0.5 * (S[1] + S[3]), -0.5 * (S[2] + S[6]), -0.5 * (S[5] + S[7])
    minor2 = p00 * p11 - p01 * p01
    det = p00 * (p11 * p22 - p12 * p12) - p01 * (p01 * p22 - p12 * p02) + p02 * (p01 * p12 - p11 * p02)
    return (p00 > 0) & (minor2 > 0) & (det > 0)


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


def _best_start_rotation(A):
    K = _horn(A)
    best = K[0]
    q = [torch.full_like(best, 2.0), torch.zeros_like(best), torch.zeros_like(best), torch.zeros_like(best)]

    def keep(value, cand):
        nonlocal best, q
        better = value > best
        best = torch.where(better, value, best)
        q = [torch.where(better, float(ci), qi) for ci, qi in zip(cand, q)]

    keep(K[5], (0, 2, 0, 0))
    keep(K[10], (0, 0, 2, 0))
    keep(K[15], (0, 0, 0, 2))
    for signs in range(8):
        s1, s2, s3 = (-1 if (signs >> b) & 1 else 1 for b in range(3))
        value = 0.5 * (s1 * K[1] + s2 * K[2] + s3 * K[3] + (s1 * s2) * K[6] + (s1 * s3) * K[7] + (s2 * s3) * K[11])
        keep(value, (1, s1, s2, s3))
    return _quaternion_rotation(*(0.5 * x for x in q))


def _horn_rotation(A):
    """Horn's method, float64, JACOBI_SWEEPS cyclic Jacobi sweeps (fixed)."""
    Ad = [a.double() for a in A]
    K = _horn(Ad)
    one, zero = torch.ones_like(Ad[0]), torch.zeros_like(Ad[0])
    V = [one if i % 5 == 0 else zero for i in range(16)]
    for _ in range(JACOBI_SWEEPS):
        for p in range(4):
            for q in range(p + 1, 4):
                apq = K[4 * p + q]
                nonzero = apq != 0
                safe = torch.where(nonzero, apq, one)
                tau = (K[5 * q] - K[5 * p]) / (2 * safe)
                t = torch.where(tau >= 0, one, -one) / (tau.abs() + torch.sqrt(1 + tau * tau))
                t = torch.where(nonzero & torch.isfinite(t), t, zero)
                c = 1 / torch.sqrt(1 + t * t)
                s = t * c
                for k in range(4):
                    akp, akq = K[4 * k + p], K[4 * k + q]
                    K[4 * k + p], K[4 * k + q] = c * akp - s * akq, s * akp + c * akq
                for k in range(4):
                    apk, aqk = K[4 * p + k], K[4 * q + k]
                    K[4 * p + k], K[4 * q + k] = c * apk - s * aqk, s * apk + c * aqk
                for k in range(4):
                    vkp, vkq = V[4 * k + p], V[4 * k + q]
                    V[4 * k + p], V[4 * k + q] = c * vkp - s * vkq, s * vkp + c * vkq
    top_val, qv = K[0], [V[0], V[4], V[8], V[12]]
    for i in range(1, 4):
        larger = K[5 * i] > top_val
        top_val = torch.where(larger, K[5 * i], top_val)
        qv = [torch.where(larger, V[4 * r + i], qv[r]) for r in range(4)]
    inv = 1 / torch.sqrt(qv[0] * qv[0] + qv[1] * qv[1] + qv[2] * qv[2] + qv[3] * qv[3])
    R = _quaternion_rotation(*(x * inv for x in qv))
    return [r.to(A[0].dtype) for r in R]


# ---------------------------------------------------------------------------
# The state machine
# ---------------------------------------------------------------------------

_INT = torch.int32


def _advance(st, steps, variant, converge, cap, eps):
    """`steps` masked Cayley steps of the kernel's advance() on state `st`."""
    A, R = st["A"], st["R"]
    running, fallback, switched = st["running"], st["fallback"], st["switched"]
    iterations, attempt, escapes = st["iterations"], st["attempt"], st["escapes"]
    tiny = torch.finfo(A[0].dtype).tiny
    undamped_tol = 3.4526698e-4 if A[0].dtype == torch.float32 else 1.4901161193847656e-8
    for _ in range(steps):
        S = _tmul(R, A)
        t = S[0] + S[4] + S[8]
        m = (S[7] - S[5], S[2] - S[6], S[3] - S[1])
        mm = m[0] * m[0] + m[1] * m[1] + m[2] * m[2]
        c = _objective_estimate(S, t, mm, variant)
        if converge and variant == "gershgorin":
            c = torch.where(switched, _objective_estimate(S, t, mm, "conservative"), c)
        w, d, ww, dd = _cayley_step(S, t, m, c)
        norm2 = dd + ww
        valid = (dd > 0) & torch.isfinite(norm2) & (norm2 > tiny)
        stepping = running & valid
        stalled = running & ~valid
        safe_d = torch.where(stepping, d, 1.0)
        safe_dd = torch.where(stepping, dd, 1.0)
        safe_w = [torch.where(stepping, x, 0.0) for x in w]
        Q = _cayley_rotation(safe_w, safe_d, torch.where(stepping, ww, 0.0), safe_dd)
        R = _where(stepping, _mul(R, Q), R)
        step_i = stepping.to(_INT)
        iterations = iterations + step_i
        attempt = attempt + step_i
        undamped = ~(c - t > undamped_tol * t.abs())
        finished = stepping & undamped & (ww < eps * dd)
        if converge:
            switch_now = (ww < ESTIMATE_SWITCH * dd) | (attempt >= GERSHGORIN_STEPS)
            switched = switched | (stepping & switch_now)
            at_max = finished & _is_maximum(S, MAX_CHECK_SLACK_EPS * eps)
            saddle = finished & ~at_max
            escape = saddle & (escapes < MAX_ESCAPES)
            fallback = fallback | (saddle & ~escape)
            R = _where(escape, _mul(R, _saddle_escape_rotation(_tmul(R, A))), R)
            escapes = escapes + escape.to(_INT)
            attempt = torch.where(escape, 0, attempt)
            switched = switched & ~escape
            finished = finished & ~escape
            exhausted = stepping & ~finished & (attempt >= cap)
            fallback = fallback | exhausted | stalled
            finished = finished | exhausted | stalled
        else:
            finished = finished | stalled | (attempt >= cap)
        running = running & ~finished
    st.update(R=R, running=running, fallback=fallback, switched=switched,
              iterations=iterations, attempt=attempt, escapes=escapes)


_LANE_KEYS = ("running", "fallback", "switched", "iterations", "attempt", "escapes")


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


def _advance_and_finish(st, steps, variant, converge, cap, eps):
    """``steps`` more Cayley steps on the lanes of ``st``, then finish():
    the Newton-Schulz clean-up and, in converged mode, the Horn fallback."""
    _advance(st, steps, variant, converge, cap, eps)
    R = _reorthonormalize(st["R"])
    if converge:
        R = _where(st["fallback"], _horn_rotation(st["A"]), R)
    return R


def fit_soa(A, R, running, variant, max_iter, eps):
    """Runs advance + finish on SoA state; returns (R list, iterations, fallback)."""
    n = running.shape[0]
    converge = max_iter is None
    cap = CONVERGED_CAP if converge else max_iter
    budget = CONVERGED_CAP * (MAX_ESCAPES + 1) if converge else max_iter
    zeros_b = torch.zeros_like(running)
    zeros_i = torch.zeros(running.shape, dtype=_INT, device=running.device)
    st = {"A": A, "R": R, "running": running, "fallback": zeros_b, "switched": zeros_b,
          "iterations": zeros_i, "attempt": zeros_i, "escapes": zeros_i}
    full = budget if (not converge and max_iter <= FULL_STEPS_MAX_ITER) else min(FULL_STEPS, budget)
    _advance(st, full, variant, converge, cap, eps)
    rest = budget - full
    capacity = straggler_capacity(n) if n > 0 else 0
    R = _reorthonormalize(st["R"])
    if capacity == 0 or (rest == 0 and not converge):
        return R, st["iterations"], st["fallback"]
    sel = st["running"] | st["fallback"]
    idx, valid, overflow = _compact_indices(sel, capacity)
    sub = {"A": [_gather(a, idx, n) for a in st["A"]], "R": [_gather(r, idx, n) for r in st["R"]]}
    for k in _LANE_KEYS:
        sub[k] = _gather(st[k], idx, n)
    sub["running"] = sub["running"] & valid
    sub["fallback"] = sub["fallback"] & valid
    R_sub = _advance_and_finish(sub, rest, variant, converge, cap, eps)
    R = [_scatter_back(r, rs, idx, valid) for r, rs in zip(R, R_sub)]
    iterations = _scatter_back(st["iterations"], sub["iterations"], idx, valid)
    fallback = _scatter_back(st["fallback"], sub["fallback"], idx, valid)
    if _COMPLETE_OVERFLOW:
        # Lanes that did not fit: the rest of the budget on the whole batch,
        # masked to them (costs the whole batch; only matters when more than
        # `capacity` lanes straggle).
        ov = dict(st)
        ov["running"] = st["running"] & overflow
        ov["fallback"] = st["fallback"] & overflow
        R_ov = _advance_and_finish(ov, rest, variant, converge, cap, eps)
        R = _where(overflow, R_ov, R)
        iterations = torch.where(overflow, ov["iterations"], iterations)
        fallback = torch.where(overflow, ov["fallback"], fallback)
    return R, iterations, fallback


_COMPLETE_OVERFLOW = True


def _components(X, n):
    """(..., 3, 3) -> 9 contiguous (n,) tensors."""
    flat = X.reshape(n, 9).t().contiguous()
    return list(flat.unbind(0))


def _normalized(M):
    max_abs = M[0].abs()
    for x in M[1:]:
        max_abs = torch.maximum(max_abs, x.abs())  # NaN propagates
    finfo = torch.finfo(M[0].dtype)
    digits = round(-math.log2(finfo.eps)) + 1
    lift = torch.where(max_abs < finfo.tiny, torch.full_like(max_abs, float(2**digits)), torch.ones_like(max_abs))
    zero = max_abs == 0
    inv = torch.where(zero, 0.0, 1 / torch.where(zero, 1.0, max_abs * lift))
    return [(x * lift) * inv for x in M], max_abs, zero


def fit_rotation_generic(M, init, max_iter, variant, return_info, bad_init_error):
    """The body of fit_rotation_reference (arguments already checked)."""
    out_dtype = M.dtype
    compute = torch.float32 if M.dtype in (torch.float16, torch.bfloat16) else M.dtype
    shape = M.shape
    batch = shape[:-2]
    n = math.prod(batch)
    eps = torch.finfo(compute).eps
    Mc = _components(M.to(compute), n)
    A, max_abs, zero = _normalized(Mc)
    finite = torch.isfinite(max_abs)
    bad_init = torch.zeros_like(finite)
    if init is not None:
        init_c = init.to(compute)
        I = [x.reshape(init.shape[:-2]) for x in _components(init_c, math.prod(init.shape[:-2]))]
        G = _gram(I)
        init_finite = torch.isfinite(G[0] + G[4] + G[8])
        dev2 = _deviation2(G)
        rotation = (dev2 < INIT_TOLERANCE**2) & (_det(I) > 0)
        init_bad = init_finite & ~rotation
        if M.device.type != "meta" and not torch.compiler.is_compiling() and bool(init_bad.any()):
            raise bad_init_error(int(init_bad.sum()), init_bad.numel())
        ex = lambda t: t.expand(batch).reshape(n)
        init_finite, init_bad, dev2 = ex(init_finite), ex(init_bad), ex(dev2)
        I = [ex(x) for x in I]
        G = [ex(g) for g in G]
        finite = finite & init_finite
        bad_init = init_bad
        clean2 = INIT_CLEAN[str(compute).removeprefix("torch.")] ** 2
        rough = init_finite & ~init_bad & ~(dev2 < clean2)
        R = I
        for _ in range(INIT_CLEAN_STEPS):
            R = _where(rough, _reorthonormalize(R, G), R)
            G = _gram(R)
            rough = rough & ~(_deviation2(G) < clean2)
    else:
        R = _best_start_rotation(A)
    A = _where(finite, A, [torch.zeros_like(a) for a in A])  # NaN stays in its lane
    running = finite & ~zero & ~bad_init
    R, iterations, fallback = fit_soa(A, R, running, variant, max_iter, eps)
    nan_lane = ~finite | bad_init
    R = [torch.where(nan_lane, float("nan"), r) for r in R]
    out = torch.stack(R, -1).reshape(shape).to(out_dtype)
    if not return_info:
        return out
    status = torch.where(fallback, STATUS_FALLBACK, STATUS_CAYLEY)
    status = torch.where(bad_init, STATUS_BAD_INIT, status)
    status = torch.where(finite, status, STATUS_NON_FINITE).to(torch.uint8)
    return out, iterations.reshape(batch), status.reshape(batch)


def rotation_tangent(X, R, M, damping):
    """csrc/kernel/rotation_gradient.h's rotation_tangent on SoA lists:
    R [u]x with u = Re (K + i lambda I)^-1 g (no K^2: float32 keeps its digits)."""
    dtype = R[0].dtype
    finfo = torch.finfo(dtype)
    A, max_abs, zero = _normalized(M)
    lift = torch.where(max_abs < finfo.tiny, torch.full_like(max_abs, float(2 ** (round(-math.log2(finfo.eps)) + 1))), torch.ones_like(max_abs))
    inv_max = torch.where(zero, 0.0, 1 / torch.where(zero, 1.0, max_abs * lift))
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
    compute = torch.float32 if R.dtype in (torch.float16, torch.bfloat16) else R.dtype
    shape = R.shape
    n = math.prod(shape[:-2])
    Gc = _components(grad.to(compute), n)
    Rc = _components(R.to(compute), n)
    Mc = _components(M.to(compute).expand(shape), n)
    T = rotation_tangent(Gc, Rc, Mc, gradient_eps)
    return torch.stack(T, -1).reshape(shape).to(out_dtype)


def fit_rotation(M, init=None, *, max_iter=None, variant="conservative", return_info=False):
    """fit_rotation_reference's contract on this module's path (the
    candidate replacement of torchrot.reference.fit_rotation_reference's body)."""
    from torchrot._checks import bad_init_error, check_all

    check_all(M, init, max_iter, variant)
    return fit_rotation_generic(M, init, max_iter, variant, return_info, bad_init_error)
