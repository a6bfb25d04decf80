"""The mat mechanics' two solvers of Newton's systems: multigrid-preconditioned conjugate gradients finds the
deflections a factorisation per step finds, on the loads a bed sees and at its extremes, and fails loudly."""

import dataclasses

import numpy as np
import pytest
import scipy.sparse as sp

from appliance.errors import ModelInputInvalid, SolverError
from appliance.sim import mechanics, multigrid
from appliance.sim.bed import BED_MAT_PARAMETERS, SMALL_MAT_PARAMETERS
from appliance.sim.mechanics import DEFAULT_PARAMETERS, solve_deflection

SAME_MM = 1e-9
"""How far the two solvers' deflections may differ, mm: Newton stops both once a full step is below 1e-11
of the depth (7e-11 mm on the bed), so their answers agree to a few such steps, far below a micrometre."""

PITCH_MM = 10.0
ROWS, COLS = np.mgrid[0:60, 0:30]
PELVIS = np.where(((ROWS - 30) / 6) ** 2 + ((COLS - 15) / 8) ** 2 < 1, 40.0, 0.0)
HEAD = np.where((ROWS - 6) ** 2 + (COLS - 15) ** 2 < 9, 6.0, 0.0)
ONE_CELL = np.where((ROWS == 5) & (COLS == 3), 0.01, 0.0)


@pytest.mark.parametrize("params, pressure, deepest", [
    (SMALL_MAT_PARAMETERS, PELVIS, 0.99),               # a pelvis on the soft foam: the liquid bottoms out
    (BED_MAT_PARAMETERS, PELVIS * 1.2 + HEAD, 0.9),     # 48 kPa, near the model's limit, on the bed mat
    (BED_MAT_PARAMETERS, PELVIS * 1e-12, 0.0),          # near-zero load
    (BED_MAT_PARAMETERS, ONE_CELL, 0.0),                # a tiny load on one cell near the clamped edge
], ids=["pelvis-bottoming-out", "pelvis-at-the-limit", "near-zero", "tiny"])
def test_multigrid_finds_the_deflection_a_factorisation_per_step_finds(params, pressure, deepest):
    direct, liquid = solve_deflection(params, pressure, PITCH_MM, solver="direct")
    found, found_liquid = solve_deflection(params, pressure, PITCH_MM, solver="multigrid")
    assert direct.max() >= deepest * params.rest_depth_mm, "the load is not as extreme as it is meant to be"
    assert direct.max() > 0
    assert np.abs(found - direct).max() <= SAME_MM
    assert found_liquid == pytest.approx(liquid, rel=1e-6, abs=1e-12)


def test_multigrid_from_a_warm_start_and_with_a_platen_and_reservoir():
    """The thesis's cell (a reservoir that fills, a rigid platen) and a warm start from the last load."""
    params = dataclasses.replace(DEFAULT_PARAMETERS, reservoir_capacity_mm3=500.0)
    pressure = np.zeros((50, 50))
    pressure[18:33, 18:33] = 8.0
    platen = pressure > 0
    last = solve_deflection(params, pressure * 0.5, 2.0, platen, solver="direct")[0]
    direct = solve_deflection(params, pressure, 2.0, platen, start_mm=last, solver="direct")[0]
    found = solve_deflection(params, pressure, 2.0, platen, start_mm=last, solver="multigrid")[0]
    assert np.abs(found - direct).max() <= SAME_MM


def test_an_unknown_solver_is_refused():
    with pytest.raises(ModelInputInvalid, match="mechanics solver must be one of multigrid, direct"):
        solve_deflection(BED_MAT_PARAMETERS, HEAD, PITCH_MM, solver="cholmod")


def test_conjugate_gradients_that_cannot_converge_raise_instead_of_returning_a_step(monkeypatch):
    monkeypatch.setattr(multigrid, "MAX_ITERATIONS", 1)
    with pytest.raises(SolverError, match="conjugate gradients on the mat mechanics reached a relative residual"):
        solve_deflection(BED_MAT_PARAMETERS, PELVIS, PITCH_MM, solver="multigrid")


def test_newton_that_cannot_converge_raises():
    with pytest.raises(SolverError, match="did not converge in 2 Newton steps"):
        solve_deflection(BED_MAT_PARAMETERS, PELVIS, PITCH_MM, max_steps=2, solver="multigrid")


def test_the_v_cycle_is_symmetric_and_positive_definite():
    """Conjugate gradients need a fixed symmetric positive definite preconditioner: the V-cycle applied to
    the columns of the identity gives a symmetric matrix with positive eigenvalues."""
    stiffness = BED_MAT_PARAMETERS.tension_n_per_m * mechanics.membrane_operator((12, 9), PITCH_MM)
    hierarchy = multigrid.MembraneHierarchy(stiffness)
    assert hierarchy.prolongators, "the grid is coarsened at least once"
    slope = np.random.default_rng(0).uniform(0.0, 30.0, stiffness.shape[0])
    cycle = hierarchy.preconditioner(sp.csr_matrix(stiffness + sp.diags(slope)))
    operator = np.column_stack([cycle(column) for column in np.identity(stiffness.shape[0])])
    assert np.abs(operator - operator.T).max() <= 1e-12 * np.abs(operator).max()
    assert np.linalg.eigvalsh(operator).min() > 0


def test_a_grid_always_gets_the_same_hierarchy_and_the_callers_random_state_is_kept():
    """pyamg draws random start vectors while building a hierarchy; seeded, two builds are identical (so a
    solve near rounding level behaves alike every run), and numpy's global generator goes on as before."""
    n = 400
    stiffness = sp.diags([-np.ones(n - 1), 2.5 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1], format="csr")
    np.random.seed(7)
    expected_next = np.random.rand()
    np.random.seed(7)
    first = multigrid.MembraneHierarchy(stiffness)
    assert np.random.rand() == expected_next
    second = multigrid.MembraneHierarchy(stiffness)
    assert len(first.prolongators) == len(second.prolongators) > 0
    assert all((p - q).count_nonzero() == 0 for p, q in zip(first.prolongators, second.prolongators))
