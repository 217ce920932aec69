"""Co-rotational elasticity: the geometric model of Chao et al. 2010 with
implicit Euler time stepping solved local-global, on a ground plane.

Per tetrahedron t with rest volume vol_t and deformation gradient F_t, the
elastic energy is mu vol_t |F_t - R_t|_F^2, R_t the rotation nearest F_t
(Chao, Pinkall, Sanan & Schroeder, "A simple geometric model for elastic
deformations", 2010: the squared distance of the gradient to SO(3)). One
implicit Euler step from positions x_n and velocities v_n minimises

    Phi(x) = 1/(2 h^2) |x - x~|_Mass^2 + mu sum_t vol_t |F_t(x) - R_t|^2,
    x~ = x_n + h v_n + h^2 g

local-global: the local step fits R_t to F_t (torchrot's convention: R_t
maximises tr(R_t^T F_t)); the global step solves the constant SPD system

    (Mass / h^2 + 2 mu L) x = Mass x~ / h^2 + 2 mu sum_t vol_t R_t G_t^T

(L = sum_t vol_t G_t G_t^T, the tetrahedral cotangent Laplacian; G_t holds the
gradients of the four barycentric coordinates), factored once.

Contact with the ground plane z = ground: at the start of each step the
vertices that inertia and gravity alone would carry below it (x~_z < ground,
which includes every vertex resting on it) form the active set; within the
step their z is held at the ground (a Dirichlet condition on z only), so the
whole body feels the contact in every global step; a vertex that the ground
had to pull down (dPhi/dz < 0 at the end of a step) is released in the next. The z system is factored
again only when the active set changes; x and y keep the constant full
system. Vertices that still end a step below the ground (rare: they were not
predicted to touch it) are put back on it. Contacting vertices lose their
normal velocity and a share of their tangential velocity (friction).

As in :mod:`torchrot.apps.arap`, the solver keeps F^T and R^T internally (the
layouts its sparse products produce and consume).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import torch

from torchrot.apps._phases import phase
from torchrot.apps.local_step import LocalStep
from torchrot.apps.sparse import SpdSolver, torch_csr

__all__ = ["ElasticState", "ElasticitySolver", "Material", "barycentric_gradients"]

Tensor = torch.Tensor


def barycentric_gradients(V: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradients of the barycentric coordinates per tetrahedron, ``(t, 4, 3)``,
    and rest volumes ``(t,)``. F_t = sum_k x_k g_{t,k}^T is the deformation
    gradient of the piecewise-linear map; sum_k g_{t,k} = 0."""
    D = np.transpose(V[T[:, 1:]] - V[T[:, :1]], (0, 2, 1))  # (t, 3, 3), columns x1-x0, x2-x0, x3-x0
    det = np.linalg.det(D)
    if np.any(det <= 0):
        raise ValueError(f"barycentric_gradients: {int(np.sum(det <= 0))} tetrahedra have non-positive volume")
    Dinv = np.linalg.inv(D)  # rows: gradients of coordinates 1..3
    G = np.concatenate([-Dinv.sum(1, keepdims=True), Dinv], 1)
    return G, det / 6.0


@dataclass
class Material:
    """Shear modulus mu (Pa), density (kg/m^3), time step h (s), gravity (m/s^2,
    along -z), ground height, friction in [0, 1] (share of tangential
    velocity removed per step in contact)."""

    mu: float = 5.0e5
    density: float = 1000.0
    dt: float = 1.0 / 60.0
    gravity: float = 9.81
    ground: float = 0.0
    friction: float = 0.2


@dataclass
class ElasticState:
    """Positions ``x`` and velocities ``v`` ``(n, 3)``, last rotations
    transposed ``Rt`` ``(t, 3, 3)`` (Rt[t] = R_t^T; None before the first
    step), ``released`` ``(n,)`` bool: vertices the ground let go of (the
    ground had to pull them in the last step), kept off contact next step."""

    x: Tensor
    v: Tensor
    Rt: Tensor | None = None
    released: np.ndarray | None = None

    @property
    def R(self) -> Tensor | None:
        return None if self.Rt is None else self.Rt.mT


@dataclass
class ElasticitySolver:
    """Implicit co-rotational elasticity for one tetrahedral mesh.

    Args:
        V: ``(n, 3)`` rest positions; T: ``(t, 4)`` positively oriented tets.
        material: :class:`Material`.
        fit: how the local step fits rotations (:meth:`step` also takes a
            ``fit`` for one time step, and a ``timer``).
        iterations: local-global iterations per time step.
        dtype: precision of the local step (deformation gradients, rotation
            fit) and of the right-hand side's product with the rotations;
            positions, energies and the solve are float64.
    """

    V: np.ndarray
    T: np.ndarray
    material: Material = field(default_factory=Material)
    fit: LocalStep = field(default_factory=LocalStep)
    iterations: int = 5
    dtype: torch.dtype = torch.float64

    def __post_init__(self) -> None:
        V = np.ascontiguousarray(self.V, dtype=np.float64)
        T = np.ascontiguousarray(self.T, dtype=np.int64)
        if V.ndim != 2 or V.shape[1] != 3 or T.ndim != 2 or T.shape[1] != 4:
            raise ValueError(f"ElasticitySolver: V must be (n, 3) and T (t, 4), got {V.shape} and {T.shape}")
        if self.iterations < 1:
            raise ValueError(f"ElasticitySolver: iterations must be >= 1, got {self.iterations}")
        n, m = len(V), len(T)
        self.n, self.m = n, m
        G, vol = barycentric_gradients(V, T)
        self.volumes = vol
        rows = np.repeat(T, 3, axis=1).ravel()  # vertex of (t, k, c)
        cols = (3 * np.arange(m)[:, None, None] + np.arange(3)).repeat(4, axis=1).ravel()  # 3t + c
        vals = G.ravel()  # g_{t,k}[c]
        # gradient operator: (D x)[3t + c] = sum_k g_{t,k}[c] x_k^T = (F_t^T)[c]
        D = sp.csr_matrix((vals, (cols, rows)), shape=(3 * m, n))
        # rhs operator: (B Rt_flat)[k] = sum_t vol_t R_t g_{t,k}, Rt_flat[3t + c] = R_t[:, c]^T
        B = sp.csr_matrix(((vals.reshape(m, 12) * vol[:, None]).ravel(), (rows, cols)), shape=(n, 3 * m))
        if self.dtype not in (torch.float32, torch.float64):
            raise ValueError(f"ElasticitySolver: dtype must be torch.float32 or torch.float64, got {self.dtype}")
        self._D64 = torch_csr(D)  # energies are always evaluated in float64
        self._D, self._B = torch_csr(D, self.dtype), torch_csr(B, self.dtype)
        self.L = sp.csr_matrix(D.T @ sp.diags(np.repeat(vol, 3)) @ D)  # sum_t vol_t G_t G_t^T
        self.mass = np.bincount(T.ravel(), weights=np.repeat(vol, 4) / 4.0, minlength=n) * self.material.density
        h, mu = self.material.dt, self.material.mu
        self._A = sp.csr_matrix(sp.diags(self.mass / h**2) + 2.0 * mu * self.L)
        self._solver = SpdSolver(self._A)
        self._active = np.zeros(n, dtype=bool)  # vertices held on the ground in the current step
        self._free_z = np.arange(n)
        self._solver_z, self._A_free_active = self._solver, None
        self.refactorizations = 0
        self.rest = torch.from_numpy(V)
        self._T = T

    # -- local-global pieces ---------------------------------------------------
    def gradients_t(self, x: Tensor, dtype: torch.dtype = torch.float64) -> Tensor:
        """F_t^T ``(t, 3, 3)`` in ``dtype`` for positions ``x`` ``(n, 3)``."""
        if dtype == torch.float64:
            return (self._D64 @ x.double()).view(self.m, 3, 3)
        return (self._D @ x.to(dtype)).view(self.m, 3, 3)

    def local_step(self, x: Tensor, Rt_prev: Tensor | None, recorder=None, meta: dict | None = None, *,
                   fit: LocalStep | None = None, timer=None) -> Tensor:
        """Fits R_t to every F_t(x), warm-started from Rt_prev; returns the new
        Rt ``(t, 3, 3)``. ``recorder(M, R_prev, meta)`` sees M = F (torchrot
        convention) and the warm start before the fit."""
        with phase(timer, "assembly"):
            Ft = self.gradients_t(x, self.dtype)
        if recorder is not None:
            recorder(Ft.mT, None if Rt_prev is None else Rt_prev.mT, meta or {})
        with phase(timer, "fit"):
            return (fit or self.fit)(Ft, Rt_prev)

    def global_step(self, Rt: Tensor, inertial_rhs: np.ndarray, *, timer=None) -> Tensor:
        """Positions ``(n, 3)`` minimising Phi for fixed rotations (given as
        Rt ``(t, 3, 3)``), the active contact vertices' z on the ground."""
        with phase(timer, "rhs"):
            rhs = inertial_rhs + 2.0 * self.material.mu * (self._B @ Rt.reshape(-1, 3)).double().numpy()
        with phase(timer, "solve"):
            x = np.empty_like(rhs)
            x[:, :2] = self._solver.solve(rhs[:, :2])
            x[:, 2] = self.material.ground
            z_rhs = rhs[self._free_z, 2]
            if self._A_free_active is not None:
                z_rhs = z_rhs - self._A_free_active @ x[self._active, 2]
            x[self._free_z, 2] = self._solver_z.solve(z_rhs)
        self._last_rhs_z = rhs[:, 2]
        return torch.from_numpy(x)

    def _set_contacts(self, active: np.ndarray, timer=None) -> None:
        """Holds the ``active`` vertices' z on the ground from now on;
        refactors the z system if the set changed."""
        if np.array_equal(active, self._active):
            return
        with phase(timer, "refactor"):
            self._active = active
            self._free_z = np.flatnonzero(~active)
            if active.any():
                A_free = self._A[self._free_z]
                self._solver_z = SpdSolver(A_free[:, self._free_z])
                self._A_free_active = sp.csr_matrix(A_free[:, np.flatnonzero(active)])
            else:
                self._solver_z, self._A_free_active = self._solver, None
            self.refactorizations += 1

    def predicted(self, state: ElasticState) -> np.ndarray:
        """x~ = x_n + h v_n - h^2 g e_z ``(n, 3)``: where inertia and gravity alone lead."""
        h = self.material.dt
        x_tilde = (state.x + h * state.v).numpy().copy()
        x_tilde[:, 2] -= h * h * self.material.gravity
        return x_tilde

    def step(self, state: ElasticState, recorder=None, frame: int = 0, energies: list | None = None, *,
             fit: LocalStep | None = None, timer=None) -> ElasticState:
        """One time step: ``iterations`` local-global iterations from x~
        (with the predicted contacts on the ground), then the contact
        clean-up. ``energies``, if given, receives Phi after every local and
        every global step (for monotonicity checks). ``fit``: the local
        step for this time step (default: the solver's); ``timer``: optional
        phase timer ("assembly", "fit", "rhs", "solve", "refactor")."""
        h = self.material.dt
        x_tilde = self.predicted(state)
        predicted = x_tilde[:, 2] < self.material.ground
        self._set_contacts(predicted if state.released is None else predicted & ~state.released, timer)
        inertial_rhs = (self.mass / h**2)[:, None] * x_tilde
        x0 = x_tilde.copy()
        x0[self._active, 2] = self.material.ground  # a feasible start
        x, Rt = torch.from_numpy(x0), state.Rt
        for iteration in range(self.iterations):
            Rt = self.local_step(x, Rt, recorder, {"frame": frame, "iteration": iteration}, fit=fit, timer=timer)
            if energies is not None:
                energies.append(self.incremental_potential(x, Rt, x_tilde))
            x = self.global_step(Rt, inertial_rhs, timer=timer)
            if energies is not None:
                energies.append(self.incremental_potential(x, Rt, x_tilde))
        released = self._adhesion(x)
        v = (x - state.x) / h
        x, v = self._ground_contact(x, v)
        return ElasticState(x, v, Rt, released)

    def _adhesion(self, x: Tensor) -> np.ndarray:
        """Active vertices the ground had to pull down (the energy would drop
        if they rose: dPhi/dz < 0): they are released in the next step."""
        pulling = np.zeros(self.n, dtype=bool)
        if self._active.any():
            active = np.flatnonzero(self._active)
            gradient = self._A[active] @ x[:, 2].numpy() - self._last_rhs_z[active]
            pulling[active] = gradient < 0
        return pulling

    def _ground_contact(self, x: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
        """Puts vertices below the ground back on it; vertices on it lose
        their normal velocity and some tangential velocity."""
        ground = self.material.ground
        x, v = x.clone(), v.clone()
        touching = x[:, 2] <= ground
        x[touching, 2] = ground
        v[touching, 2] = v[touching, 2].clamp_min(0.0)
        v[touching, :2] *= 1.0 - self.material.friction
        return x, v

    # -- energy ----------------------------------------------------------------
    def incremental_potential(self, x: Tensor, Rt: Tensor | None, x_tilde: np.ndarray) -> float:
        """Phi(x, R) of one time step (R = the optimal rotations if Rt is None)."""
        Ft = self.gradients_t(x)
        Rt = LocalStep("converged")(Ft, None) if Rt is None else Rt.double()
        vol = torch.from_numpy(self.volumes)
        elastic = self.material.mu * float((vol * ((Ft - Rt) ** 2).sum((-2, -1))).sum())
        d = x.numpy() - x_tilde
        inertia = float(np.sum(self.mass[:, None] * d * d)) / (2.0 * self.material.dt**2)
        return inertia + elastic

    def elastic_energy(self, x: Tensor) -> float:
        """mu sum_t vol_t dist(F_t, SO(3))^2 of positions ``x`` ``(n, 3)``."""
        Ft = self.gradients_t(x)
        Rt = LocalStep("converged")(Ft, None)
        return self.material.mu * float((torch.from_numpy(self.volumes) * ((Ft - Rt) ** 2).sum((-2, -1))).sum())

    def initial_state(self, lift: float = 0.25, tilt_degrees: float = 20.0, spin: float = 1.0) -> ElasticState:
        """The rest shape tilted about x by ``tilt_degrees``, its lowest point
        ``lift`` above the ground, spinning at ``spin`` rad/s about z."""
        a = np.radians(tilt_degrees)
        Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
        V = self.rest.numpy()
        centre = V.mean(0)
        x = (V - centre) @ Rx.T
        x[:, 2] += self.material.ground + lift - x[:, 2].min()
        x[:, :2] += centre[:2]
        c = x.mean(0)
        v = spin * np.stack([-(x[:, 1] - c[1]), x[:, 0] - c[0], np.zeros(len(x))], -1)
        return ElasticState(torch.from_numpy(x), torch.from_numpy(v))
