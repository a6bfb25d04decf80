"""Calibration cost: how many sparse and dense factorisations the bed's pressure calibration makes, where,
and how long it takes, with the mat mechanics' Newton systems solved by multigrid-preconditioned conjugate
gradients (as the appliance solves them) and by one sparse factorisation a Newton step (as it did before).

    python benchmarks/calibration_cost.py      # writes benchmarks/calibration_cost.md (about 15 minutes)

The calibration is the one the package ships for the bed (`appliance calibrate pressure --layout grid-16x32
--maps ../shared/data/pmatdata --subjects 1,2,3,5,7,8,9,10`): PmatData's 136 maps laid on the virtual bed in
turn, read through the whole chain and imaged. It is made twice, once with each mechanics solver, and every
factorisation call (SuperLU, LU and Cholesky, sparse or dense, incomplete too) is counted by the function that
made it. The mechanics' solves of the factorising run are then replayed with each solver in turn, in the same
process, ``REPEATS`` times alternately: their seconds (median), Newton steps, conjugate-gradient iterations and
how far the deflections move.
"""

from __future__ import annotations

import appliance  # noqa: F401  (first: it pins BLAS to one thread before numpy loads)

import collections
import sys
import time
from pathlib import Path

import numpy as np
import scipy.linalg
import scipy.sparse.linalg

from appliance.calibration import pressure_calibration
from appliance.core.model_cache import cached_model, default_cache_dir, default_setup
from appliance.core.named_layouts import get_layout
from appliance.drivers.profile import board_profile
from appliance.service.virtual_bed import VirtualBedSource, shipped_calibration
from appliance.sim import mechanics, multigrid
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
FACTORISERS = ((scipy.sparse.linalg, "splu"), (scipy.sparse.linalg, "spilu"), (scipy.sparse.linalg, "factorized"),
               (scipy.linalg, "cho_factor"), (scipy.linalg, "cholesky"), (scipy.linalg, "lu_factor"),
               (scipy.linalg, "lu"), (np.linalg, "cholesky"))
REPEATS = 3                         # replays of the mechanics' solves per solver, alternating; the median is shown
SOLVERS = ("direct", "multigrid")   # before, and as the appliance now solves


class Counted:
    """While open: every factorisation call, by the module and function that made it; the multigrid
    hierarchies set up, the Newton steps and the conjugate-gradient iterations of the mechanics."""

    def __init__(self):
        self.calls = collections.Counter()
        self.setups = self.steps = self.iterations = 0
        self._saved = []

    def __enter__(self):
        for module, name in FACTORISERS:
            self._patch(module, name, self._counting)
        self._patch(multigrid.MembraneHierarchy, "__init__", self._tallied("setups"))
        self._patch(multigrid.InexactSteps, "solve", self._tallied("steps"))
        self._patch(mechanics._DirectSteps, "solve", self._tallied("steps"))
        self._patch(multigrid, "conjugate_gradients", self._iterating)
        return self

    def __exit__(self, *exc):
        for owner, name, original in reversed(self._saved):
            setattr(owner, name, original)
        self._saved.clear()

    def _patch(self, owner, name, wrap):
        original = getattr(owner, name)
        self._saved.append((owner, name, original))
        setattr(owner, name, wrap(original))

    def _counting(self, original):
        def counted(*args, **kwargs):
            caller = sys._getframe(1).f_code
            self.calls[f"{Path(caller.co_filename).name}:{caller.co_name}"] += 1
            return original(*args, **kwargs)
        return counted

    def _tallied(self, tally):
        def wrap(original):
            def tallied(*args, **kwargs):
                setattr(self, tally, getattr(self, tally) + 1)
                return original(*args, **kwargs)
            return tallied
        return wrap

    def _iterating(self, original):
        def iterating(*args, **kwargs):
            x, iterations = original(*args, **kwargs)
            self.iterations += iterations
            return x, iterations
        return iterating


def calibrate(loads, solver):
    """The shipped calibration's procedure, as ``appliance calibrate pressure --maps`` runs it on the virtual
    source, with the mechanics' ``solver``; returns it, its counts, its seconds, and the mechanics solves
    it made (their inputs and results)."""
    layout = get_layout(LAYOUT)
    setup = default_setup(layout)
    model, _ = cached_model(setup, default_cache_dir())
    source = VirtualBedSource(layout, empty_mat(layout), setup.protocol, seed=0,
                              profile=board_profile(virtual_board(layout)))
    mechanics._bordered_system.cache_clear()            # each run sets its grid up afresh, and is counted doing so
    solves, solve = [], mechanics.solve_deflection

    def recorded(params, pressure, pitch, platen=None, start_mm=None, max_steps=100, solver=solver):
        result = solve(params, pressure, pitch, platen, start_mm, max_steps, solver)
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
    return calibration, counted, seconds, solves


def replay(solves):
    """The recorded mechanics solves again with each solver, ``REPEATS`` times alternately: per solver its
    counts (of the last repeat), median seconds, and the largest change of a deflection from the recorded."""
    seconds = {solver: [] for solver in SOLVERS}
    counts, deviation = {}, dict.fromkeys(SOLVERS, 0.0)
    for _ in range(REPEATS):
        for solver in SOLVERS:
            with Counted() as counted:
                start = time.perf_counter()
                found = [mechanics.solve_deflection(params, pressure, pitch, platen, start_mm, solver=solver)[0]
                         for params, pressure, pitch, platen, start_mm, _ in solves]
                seconds[solver].append(time.perf_counter() - start)
            counts[solver] = counted
            deviation[solver] = max(float(np.abs(w - result[0]).max()) for w, (*_, result) in zip(found, solves))
    return {solver: (counts[solver], float(np.median(seconds[solver])), deviation[solver]) for solver in SOLVERS}


def curve_change(calibration, reference) -> float:
    """The largest difference between two calibrations' curves, kPa, at the reference's points."""
    return float(np.max(np.abs(np.interp(reference.curve.change, calibration.curve.change,
                                         calibration.curve.pressure) - reference.curve.pressure)))


def main():
    if not PMAT.is_dir():
        sys.exit(f"PmatData is not at {PMAT}: the bed's calibration is made from it")
    loads = pmat_map_loads(PMAT, SUBJECTS)
    shipped = shipped_calibration(LAYOUT)
    runs = {}
    for solver in SOLVERS:
        runs[solver] = calibrate(loads, solver)
        print(solver, dict(runs[solver][1].calls), f"{runs[solver][2]:.0f} s", flush=True)
    replayed = replay(runs["direct"][3])
    print({solver: (dict(c.calls), s, d) for solver, (c, s, d) in replayed.items()}, flush=True)
    params, pressure, pitch, *_ = runs["direct"][3][-1]
    hierarchy = mechanics._bordered_system(pressure.shape, float(pitch), params.tension_n_per_m, None).hierarchy
    (HERE / "calibration_cost.md").write_text(render(len(loads), runs, replayed, shipped, hierarchy))
    print((HERE / "calibration_cost.md").read_text())


def mechanics_factorisations(calls) -> int:
    """Factorisations of the mat mechanics' own matrices (the grid's ordering and projector, Newton's systems)."""
    return sum(n for site, n in calls.items() if site.startswith("mechanics.py"))


def render(n_loads, runs, replayed, shipped, hierarchy) -> str:
    sites = sorted({site for _, counted, _, _ in runs.values() for site in counted.calls},
                   key=lambda site: -runs["direct"][1].calls[site])
    direct, multigrid_run = runs["direct"], runs["multigrid"]
    coarsest = hierarchy.prolongators[-1].shape[1]
    levels = " -> ".join(str(p.shape[0]) for p in hierarchy.prolongators) + f" -> {coarsest}"
    names = {"direct": "a factorisation per Newton step (before)", "multigrid": "multigrid and conjugate gradients"}
    calibration_rows = [[names[solver], mechanics_factorisations(c.calls),
                         c.calls["multigrid.py:preconditioner"], c.setups, c.steps, f"{seconds:.0f}",
                         f"{curve_change(calibration, shipped):.3g}"]
                        for solver, (calibration, c, seconds, _) in runs.items()]
    replay_rows = [[names[solver], mechanics_factorisations(c.calls), c.calls["multigrid.py:preconditioner"],
                    c.steps, c.iterations, f"{seconds:.1f}", f"{deviation:.2g}"]
                   for solver, (c, seconds, deviation) in replayed.items()]
    ratio = replayed["direct"][1] / replayed["multigrid"][1]
    return f"""# Calibration cost: factorisations of the bed's pressure calibration

Made by `{COMMAND}` on {machine()}.

The calibration the package ships for the bed, made again: `{LAYOUT}`, PmatData's maps of subjects
{", ".join(map(str, SUBJECTS))} ({n_loads} maps) laid on the virtual bed in turn, read by the parallel board's chain
and imaged as the monitor images them (`appliance calibrate pressure --maps`). It is made twice in this process,
once with each way of solving the mat mechanics' Newton systems (`solve_deflection`'s `solver`): by one sparse
factorisation per Newton step, as the appliance did before, and by conjugate gradients preconditioned by a
multigrid hierarchy of the membrane made once for the grid, as it does now (`appliance/sim/multigrid.py`).

## The calibration, made with each solver

{table(["mechanics solved by", "factorisations of the mat mechanics",
        f"coarsest-level Cholesky ({coarsest} x {coarsest})", "multigrid setups", "Newton steps", "seconds",
        "curve against the shipped, kPa"], calibration_rows)}

The two calibrations' curves differ by at most {curve_change(multigrid_run[0], direct[0]):.2g} kPa; the same virtual mat
as the shipped calibration's: {"yes" if multigrid_run[0].notes["mat"] == shipped.notes["mat"] else "no"}. Each run's
seconds are the whole calibration's (the chain, the transfer solves and the imaging too), one run each on a
shared machine: the replay below times the mechanics alone.

## Factorisations, by where they are made

{table(["made by", *[names[solver] for solver in runs]], [[site, *[c.calls[site] for _, c, _, _ in runs.values()]]
                                                        for site in sites])}

`mechanics.py:solve` is the factorisation of a Newton step's system (one a step); `mechanics.py:_bordered_system`
the grid's fill-reducing ordering and its projector, once per grid. `multigrid.py:preconditioner` is the dense
Cholesky of the hierarchy's coarsest level, {coarsest} unknowns (the mat has {hierarchy.prolongators[0].shape[0]}),
once per Newton step: not a factorisation of the mat's mechanics but of a {coarsest} x {coarsest} matrix; the
hierarchy's setup (smoothed aggregation of the membrane's stiffness, levels {levels}) factorises nothing. The rest are
the transfer solves (one a map) and the reconstruction's.

## The mechanics' solves replayed

The {len(direct[3])} mechanics solves of the factorising run (the same loads and warm starts), solved again with
each solver in this process, {REPEATS} times alternately (median seconds). Newton's stopping rule is the same for both (a full
step below 1e-11 of the liquid's depth); the multigrid solver solves each step's systems only as tightly as
Newton's progress can use (forcing terms of Eisenstat and Walker, from a tenth of the residual down to 1e-10).

{table(["mechanics solved by", "factorisations of the mat mechanics", "coarsest-level Cholesky", "Newton steps",
        "conjugate-gradient iterations", "seconds", "largest deflection change, mm"], replay_rows)}

The mechanics take {ratio:.2g} times less time with multigrid. A factorisation serves one Newton system only:
each map moves the foundation's slope over the body's whole footprint, and before this the last factorisation
kept as the preconditioner of conjugate gradients cut the mechanics' factorisations from 1493 to 565 at the same
time (64.8 s against 61.9 s). The multigrid hierarchy holds across the whole range of slopes because it is built
on the membrane alone: where the foundation is stiff the system is diagonally dominant and Gauss-Seidel damps
the error by itself, and where it is slack the membrane's smooth modes are what the coarse levels carry.
"""


if __name__ == "__main__":
    main()
