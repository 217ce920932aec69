"""torchrot.apps: meshes, the local step (rotation fits), ARAP against libigl
and elasticity. Small meshes only (a few seconds)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("scipy")
igl = pytest.importorskip("igl")

import torchrot  # noqa: E402
from torchrot.apps.arap import ArapSolver  # noqa: E402
from torchrot.apps.elasticity import ElasticitySolver  # noqa: E402
from torchrot.apps.local_step import LocalStep, keep_better  # noqa: E402
from torchrot.apps.meshes import capsule, load_surface, octopus  # noqa: E402
from torchrot.bench import experiments  # noqa: E402
from torchrot.bench.sessions import HandleScript, run_arap_session  # noqa: E402
from torchrot.testing import random_rotations  # noqa: E402


# -- meshes -------------------------------------------------------------------------
def test_capsule_is_a_closed_outward_surface():
    mesh = capsule(8, half_length=1.0)
    assert len(mesh.V) == 6 * 8**2 + 2 + 4 * 8 * 8  # cube sphere + 8 rings of 32 vertices
    assert igl.euler_characteristic(mesh.F) == 2
    assert igl.is_edge_manifold(mesh.F)[0]
    # outward orientation: the signed volume (divergence theorem) is positive and close to the capsule's
    a, b, c = (mesh.V[mesh.F[:, k]] for k in range(3))
    volume = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6
    exact = 4 / 3 * np.pi + np.pi * 2.0
    assert 0.97 * exact < volume < exact


def test_capsule_rejects_odd_resolution():
    with pytest.raises(ValueError, match="resolution"):
        capsule(7)


def test_octopus_tets_are_positive_and_connected():
    mesh = octopus(8)
    assert mesh.is_volume
    assert np.all(igl.volume(mesh.V, mesh.F) > 0)
    assert mesh.V[:, 2].min() == 0.0
    from scipy.sparse.csgraph import connected_components

    assert connected_components(igl.adjacency_matrix(mesh.F))[0] == 1


def test_default_meshes_are_large_enough():
    assert len(capsule().V) >= 50_000
    assert len(octopus().F) >= 20_000


def test_load_surface_round_trip(tmp_path):
    mesh = capsule(4)
    path = str(tmp_path / "capsule.obj")
    igl.writeOBJ(path, mesh.V, mesh.F)
    loaded = load_surface(path)
    assert loaded.V.shape == mesh.V.shape and loaded.F.shape == mesh.F.shape
    np.testing.assert_allclose(loaded.V, mesh.V, atol=1e-6)
    with pytest.raises(FileNotFoundError, match="no mesh file"):
        load_surface(str(tmp_path / "missing.obj"))


# -- local step ---------------------------------------------------------------------
def test_rotation_fit_methods_agree_and_reject_unknown():
    gen = torch.Generator().manual_seed(0)
    R_prev = random_rotations(200, gen)
    M = R_prev @ random_rotations(200, gen, max_angle=0.05) @ torch.diag(torch.tensor([3.0, 2.0, 1.0],
                                                                                     dtype=torch.float64))
    exact = torchrot.rotation_svd(M)
    for method in ("svd", "converged"):
        assert (LocalStep(method)(M, R_prev) - exact).abs().max() < 1e-12
    one = LocalStep("one_step")(M, R_prev)
    assert (one - exact).abs().max() < 1e-4
    with pytest.raises(ValueError, match="method"):
        LocalStep("qr")
    with pytest.raises(ValueError, match="variant"):
        LocalStep("one_step", variant="damped")


def test_keep_better_restores_worse_rotations():
    M = torch.eye(3, dtype=torch.float64).expand(2, 3, 3)
    R_prev = torch.eye(3, dtype=torch.float64).expand(2, 3, 3).clone()
    R = R_prev.clone()
    R[1] = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))  # worse for M = I
    assert keep_better(R, R_prev, M) == 1
    assert torch.equal(R, R_prev)


# -- ARAP -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def validation():
    """Every fit and igl.arap_solve from the same start on a small capsule."""
    return experiments.validate_arap_against_libigl(capsule(6), HandleScript(frames=40), iterations=300,
                                                    start_frame=10, jump_frames=2)


@pytest.mark.parametrize("fit", ["svd", "one_step", "converged"])
def test_arap_converged_energy_matches_libigl(validation, fit):
    result = validation["fits"][fit]
    assert result["last_relative_change"] < 1e-9, "not converged: the comparison would be meaningless"
    assert abs(result["relative_difference_to_libigl"]) < 1e-6
    assert abs(result["relative_difference_to_svd"]) < 1e-6


@pytest.mark.parametrize("fit", ["svd", "one_step", "converged"])
def test_arap_energy_never_increases(validation, fit):
    assert validation["fits"][fit]["max_relative_increase"] <= 1e-10


def test_arap_session_energy_monotone_and_handles_exact():
    mesh = capsule(6)
    script = HandleScript(frames=5)
    handles, moving = script.handles(mesh.V)
    solver = ArapSolver(mesh.V, mesh.F, handles, LocalStep("one_step"))
    energies: list = []
    state = run_arap_session(solver, script, 3, energies=energies)
    tolerance = 1e-10 * max(e for *_, e in energies)  # rounding of the energy evaluation
    previous = None
    for _frame, iteration, after_local, after_global in energies:
        if previous is not None:
            assert after_local <= previous + tolerance  # local step: same positions, better rotations
        if iteration > 0:  # (the first global step of a frame moves the handles: a new problem)
            assert after_global <= after_local + tolerance
        previous = after_global
    # the handles sit on their last targets, the rotations are rotations
    np.testing.assert_allclose(state.P.numpy()[handles], script.targets(mesh.V, script.frames - 1), atol=1e-12)
    R = state.R
    assert torch.allclose(R.mT @ R, torch.eye(3, dtype=R.dtype).expand_as(R), atol=1e-12)


def test_arap_float32_local_step_reaches_the_same_energy():
    mesh = capsule(6)
    script = HandleScript(frames=5)
    handles, _ = script.handles(mesh.V)
    finals = []
    for dtype in (torch.float64, torch.float32):
        solver = ArapSolver(mesh.V, mesh.F, handles, LocalStep("converged"), dtype=dtype)
        state = run_arap_session(solver, script, 40)
        assert state.Rt.dtype == dtype
        finals.append(solver.energy(state.P))
    assert abs(finals[1] - finals[0]) <= 1e-5 * finals[0]


def test_arap_rejects_bad_arguments():
    mesh = capsule(4)
    with pytest.raises(ValueError, match="handles"):
        ArapSolver(mesh.V, mesh.F, np.array([len(mesh.V)]))
    with pytest.raises(ValueError, match="dtype"):
        ArapSolver(mesh.V, mesh.F, np.array([0]), dtype=torch.float16)


# -- elasticity -------------------------------------------------------------------------
def test_elasticity_falls_lands_and_stays_finite_above_ground():
    mesh = octopus(8)
    solver = ElasticitySolver(mesh.V, mesh.F, iterations=3)
    np.testing.assert_allclose((solver.L + igl.cotmatrix(mesh.V, mesh.F)).toarray(), 0, atol=1e-12)
    state = solver.initial_state(lift=0.2)
    z0 = state.x[:, 2].mean().item()
    lowest = []
    for frame in range(40):
        energies: list = []
        state = solver.step(state, frame=frame, energies=energies)
        assert all(b <= a * (1 + 1e-10) for a, b in zip(energies, energies[1:])), "energy rose within a step"
        assert torch.isfinite(state.x).all() and torch.isfinite(state.v).all()
        lowest.append(state.x[:, 2].min().item())
    assert min(lowest) >= solver.material.ground  # never below the ground
    assert lowest[-1] == solver.material.ground  # resting on it
    assert state.x[:, 2].mean().item() < z0  # it fell
    assert solver.refactorizations >= 1
