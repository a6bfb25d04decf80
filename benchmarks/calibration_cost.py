"""Calibration cost: how many sparse and dense factorisations the bed's pressure calibration makes, where,
and what reusing the mat mechanics' factorisations across Newton steps and maps would buy.

    python benchmarks/calibration_cost.py      # writes benchmarks/calibration_cost.md (about 10 minutes)

The calibration is the one the package ships for the bed (`appliance calibrate pressure --layout grid-16x32
--maps ../shared/data/pmatdata --subjects 1,2,3,5,7,8,9,10`): PmatData's 136 maps laid on the virtual bed in
turn, read through the whole chain and imaged. Every factorisation call (SuperLU, Cholesky, ``factorized``) is
counted by the function that made it. The mat mechanics' solves are recorded as they ran and replayed twice in
the same process: as the appliance solves them (one factorisation per Newton step), and with the last
factorisation kept as the preconditioner of conjugate gradients (inexact Newton: each step's linear system
solved to a tenth of its residual in at most four iterations, else factorised anew), to say whether reuse pays.
"""

from __future__ import annotations

import appliance  # noqa: F401  (first: it pins BLAS to one thread before numpy loads)

import collections
import sys
import time
from pathlib import Path

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg

from appliance.calibration import pressure_calibration
from appliance.core.model_cache import cached_model, default_cache_dir, default_setup
from appliance.core.named_layouts import get_layout
from appliance.drivers.profile import board_profile
from appliance.service.virtual_bed import VirtualBedSource, shipped_calibration
from appliance.sim import mechanics
from appliance.sim.frontend import virtual_board
from appliance.sim.loads import empty_mat
from appliance.sim.recordings import pmat_map_loads

sys.path.insert(0, str(Path(__file__).parent))
from report import machine, table  # noqa: E402

HERE = Path(__file__).parent
COMMAND = "python benchmarks/calibration_cost.py"
PMAT = HERE.parent.parent / "shared" / "data" / "pmatdata"
LAYOUT = "grid-16x32"
SUBJECTS = (1, 2, 3, 5, 7, 8, 9, 10)
FACTORISERS = ((scipy.sparse.linalg, "splu"), (scipy.sparse.linalg, "factorized"), (scipy.linalg, "cho_factor"),
               (scipy.linalg, "cholesky"), (np.linalg, "cholesky"))
REUSE_TOLERANCE = 0.1               # each Newton step's linear residual, relative, with the kept factor
REUSE_ITERATIONS = 4                # conjugate-gradient iterations allowed before factorising anew


class Counted:
    """Every factorisation call while open, by the module and function that made it."""

    def __init__(self):
        self.calls = collections.Counter()
        self._saved = []

    def __enter__(self):
        for module, name in FACTORISERS:
            original = getattr(module, name)
            self._saved.append((module, name, original))
            setattr(module, name, self._counting(original))
        return self

    def __exit__(self, *exc):
        for module, name, original in self._saved:
            setattr(module, name, original)

    def _counting(self, original):
        def counted(*args, **kwargs):
            caller = sys._getframe(1).f_code
            self.calls[f"{Path(caller.co_filename).name}:{caller.co_name}"] += 1
            return original(*args, **kwargs)
        return counted


def calibrate(loads):
    """The shipped calibration's procedure, as ``appliance calibrate pressure --maps`` runs it on the virtual
    source; returns it, its factorisations by site, its seconds, and the mechanics solves it made."""
    layout = get_layout(LAYOUT)
    setup = default_setup(layout)
    model, _ = cached_model(setup, default_cache_dir())
    source = VirtualBedSource(layout, empty_mat(layout), setup.protocol, seed=0,
                              profile=board_profile(virtual_board(layout)))
    solves, solve = [], mechanics.solve_deflection

    def recorded(params, pressure, pitch, platen=None, start_mm=None, max_steps=100):
        result = solve(params, pressure, pitch, platen, start_mm, max_steps)
        solves.append((params, np.array(pressure), pitch, platen, None if start_mm is None else np.array(start_mm),
                       result))
        return result

    mechanics.solve_deflection = recorded
    try:
        with Counted() as counted:
            start = time.perf_counter()
            calibration = source.stamped(pressure_calibration(source.acquire, source.place, model, loads), model)
            seconds = time.perf_counter() - start
    finally:
        mechanics.solve_deflection = solve
    return calibration, counted.calls, seconds, solves


class KeptFactor:
    """The mechanics' Newton systems solved with the last factorisation kept: conjugate gradients
    preconditioned by it, to ``REUSE_TOLERANCE`` of the residual within ``REUSE_ITERATIONS``, else a new
    factorisation of the system at hand."""

    def __init__(self):
        self.factor, self.factorisations, self.iterations = None, 0, 0

    def solve(self, matrix, rhs):
        if self.factor is not None:
            x = self._conjugate_gradients(matrix, rhs)
            if x is not None:
                return x
        self.factor = scipy.sparse.linalg.splu(matrix, permc_spec="NATURAL", diag_pivot_thresh=0.0,
                                               options={"SymmetricMode": True})
        self.factorisations += 1
        return self.factor.solve(rhs)

    def _conjugate_gradients(self, matrix, rhs):
        x = self.factor.solve(rhs)
        r = rhs - matrix @ x
        target = REUSE_TOLERANCE * np.linalg.norm(rhs, axis=0)
        z = self.factor.solve(r)
        p, rz = z.copy(), (r * z).sum(axis=0)
        for _ in range(REUSE_ITERATIONS):
            if (np.linalg.norm(r, axis=0) <= target).all():
                return x
            self.iterations += 1
            q = matrix @ p
            a = rz / (p * q).sum(axis=0)
            x, r = x + a * p, r - a * q
            z = self.factor.solve(r)
            rz, previous = (r * z).sum(axis=0), rz
            p = z + rz / previous * p
        return x if (np.linalg.norm(r, axis=0) <= target).all() else None


def newton_with(params, pressure, pitch, start_mm, kept: KeptFactor, max_steps=200):
    """The bed mat's deflection as :func:`appliance.sim.mechanics.solve_deflection` finds it (no platen, no
    reservoir: the bed's case), each Newton system solved by ``kept``; the same stopping rule."""
    shape = pressure.shape
    p = pressure.ravel()
    if not p.any():
        return np.zeros(shape)
    system = mechanics._bordered_system(shape, float(pitch), params.tension_n_per_m, None)
    basis, stiffness, volume = system.basis, system.stiffness, system.volume
    load = system.basis_t @ p
    d0 = params.rest_depth_mm
    ceiling = d0 - 0.5 * params.foundation_kpa_per_mm * params.contact_mm**2 / params.max_pressure_kpa
    u = np.zeros(volume.size) if start_mm is None else \
        system.projector.solve(system.basis_t @ np.clip(np.ravel(start_mm), -d0, ceiling))
    deepest = float((basis @ u).max())
    if not np.isfinite(deepest):
        u = np.zeros(volume.size)
    elif deepest > ceiling:
        u *= ceiling / deepest
    w, liquid = basis @ u, 0.0
    for _ in range(max_steps):
        force, slope = mechanics.foundation_force(params, w)
        residual = stiffness @ u + system.basis_t @ force + liquid * volume - load
        matrix = sp.csc_matrix(stiffness + system.basis_t @ sp.diags(slope) @ basis)
        x = kept.solve(matrix, np.column_stack([-residual, volume]))
        liquid_step = (volume @ x[:, 0] + volume @ u) / (volume @ x[:, 1])
        step = x[:, 0] - liquid_step * x[:, 1]
        w_step = basis @ step
        deeper = w_step > 0
        t = min(1.0, 0.9 * float(np.min((d0 - w[deeper]) / w_step[deeper]))) if deeper.any() else 1.0
        u, liquid = u + t * step, liquid + t * liquid_step
        w = basis @ u
        if t == 1.0 and np.abs(w_step).max() <= 1e-11 * d0:
            return w.reshape(shape)
    raise RuntimeError("no convergence with the kept factor")


def replay(solves):
    """The recorded mechanics solves again: as the appliance makes them, and with the factor kept."""
    with Counted() as counted:
        start = time.perf_counter()
        for params, pressure, pitch, platen, start_mm, _ in solves:
            mechanics.solve_deflection(params, pressure, pitch, platen, start_mm)
        landed_s = time.perf_counter() - start
    kept = KeptFactor()
    start = time.perf_counter()
    deviation = 0.0
    for params, pressure, pitch, platen, start_mm, (deflection, _) in solves:
        if platen is not None or params.reservoir_mm3_per_kpa > 0:
            raise RuntimeError("the replay covers the bed mat's case only: no platen, no reservoir")
        deviation = max(deviation, float(np.abs(newton_with(params, pressure, pitch, start_mm, kept)
                                                - deflection).max()))
    kept_s = time.perf_counter() - start
    return {"landed": (sum(counted.calls.values()), landed_s), "kept": (kept.factorisations, kept_s),
            "iterations": kept.iterations, "deviation_mm": deviation}


def main():
    if not PMAT.is_dir():
        sys.exit(f"PmatData is not at {PMAT}: the bed's calibration is made from it")
    loads = pmat_map_loads(PMAT, SUBJECTS)
    calibration, calls, seconds, solves = calibrate(loads)
    shipped = shipped_calibration(LAYOUT)
    same_curve = float(np.max(np.abs(np.interp(shipped.curve.change, calibration.curve.change,
                                                calibration.curve.pressure) - shipped.curve.pressure)))
    print(dict(calls), f"{seconds:.0f} s", flush=True)
    replayed = replay(solves)
    print(replayed, flush=True)
    (HERE / "calibration_cost.md").write_text(render(len(loads), calls, seconds, replayed, same_curve,
                                                     calibration.notes["mat"] == shipped.notes["mat"]))
    print((HERE / "calibration_cost.md").read_text())


def render(n_loads, calls, seconds, replayed, same_curve, same_mat) -> str:
    mechanics_calls = sum(n for site, n in calls.items() if site.startswith("mechanics.py"))
    sites = [[site, n] for site, n in calls.most_common()]
    landed_n, landed_s = replayed["landed"]
    kept_n, kept_s = replayed["kept"]
    return f"""# Calibration cost: factorisations of the bed's pressure calibration

Made by `{COMMAND}` on {machine()}.

The calibration the package ships for the bed, made again: `{LAYOUT}`, PmatData's maps of subjects
{", ".join(map(str, SUBJECTS))} ({n_loads} maps) laid on the virtual bed in turn, read by the parallel board's chain
and imaged as the monitor images them (`appliance calibrate pressure --maps`). It took {seconds:.0f} s; its curve
differs from the shipped one by at most {same_curve:.3g} kPa (the same virtual mat: {"yes" if same_mat else "no"}).

## Factorisations, by where they are made

{table(["made by", "calls"], sites)}

{sum(calls.values())} in all, {mechanics_calls} of them the mat mechanics (`solve_deflection`: one sparse factorisation
per Newton step of each map's deflection; `_bordered_system`: the grid's ordering and projector, once per grid).
Each map moves the membrane's foundation slope (the liquid's slack and the barrier near the base) over the
body's whole footprint, and the first steps of each solve move it over most of the mat, so no two Newton
systems of a calibration share a matrix, nor differ by a low-rank update.

## Reusing the factorisation: the mechanics' solves replayed

The mechanics' solves recorded above ({landed_n} factorisations), replayed in this process: as the
appliance makes them, and with the last factorisation kept as the preconditioner of conjugate gradients
(each Newton step's system solved to {REUSE_TOLERANCE:g} of its residual within {REUSE_ITERATIONS} iterations, else
factorised anew; Newton's own stopping rule, a step below 1e-11 of the liquid's depth, unchanged).

{table(["mechanics solves", "factorisations", "seconds", "conjugate-gradient iterations",
        "largest deflection change, mm"],
       [["as the appliance makes them", landed_n, f"{landed_s:.1f}", 0, 0],
        ["factor kept as preconditioner", kept_n, f"{kept_s:.1f}", replayed["iterations"],
         f"{replayed['deviation_mm']:.2g}"]])}

A kept factor serves a Newton system only while the slope field is close to its own: from one map to the next,
or between a solve's first steps, conjugate gradients need as many triangular solves (each about a twentieth of
a factorisation here) as a new factorisation costs, so reuse trades factorisations for solves at about the same
time. Fewer than 50 factorisations for the {n_loads} maps would need a preconditioner that holds across the whole
range of slopes without being refactorised (multigrid on the cell grid), not a reused factorisation.
"""


if __name__ == "__main__":
    main()
