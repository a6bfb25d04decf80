"""Simulator benchmark: virtual-bed frames per second, where a moving frame's time goes, and the detail a bed needs.

    python benchmarks/simulator.py        # writes benchmarks/simulator.md and simulator.png

A frame is ``VirtualFrontEnd.acquire()``: the bed's transfer impedances at the
frame's scene time (``VirtualBed.transfer_ohm``) and the whole-frame analogue
chain on them. The bed re-solves only when the scene or the temperature changed
("cache"); without the cache every frame is forced to re-solve by putting the
same scene back on the mat first. The re-solve's electrode part is either the
transfer alone from one factorisation (``solver="block"``) or a field per
electrode (``solver="fields"``). Whether a local update (low-rank, or a warm
iterative start) could beat the re-solve is measured on the scenes' own changes.
"""

from __future__ import annotations

import appliance  # noqa: F401  (first: it pins BLAS to one thread before numpy loads)

import inspect
import os
import sys
import time
from pathlib import Path

import numpy as np

from appliance.core.fem import build_fem_model
from appliance.core.forward import factorise, solve_electrodes
from appliance.core.named_layouts import get_layout
from appliance.core.protocols import default_protocol
from appliance.drivers.profile import board_profile
from appliance.sim.bed import VirtualBed, mat_parameters_for
from appliance.sim.body import MatGrid
from appliance.sim.field import PressureField
from appliance.sim.frontend import VirtualFrontEnd
from appliance.sim.mechanics import conductance_on_model, sheet_conductance
from appliance.sim.scene_base import CHANGE_TOLERANCE_KPA, Scene
from appliance.sim.scenes import load_scene
from appliance.sim.transfer import TransferSolver

sys.path.insert(0, str(Path(__file__).parent))
from report import machine, median_seconds, pyplot, save_figure, table  # noqa: E402

HERE = Path(__file__).parent
COMMAND = "python benchmarks/simulator.py"
BED = "grid-16x32"
FRAMES = 8
WINDOWS = {"supine-still": (600.0, "still"), "restless": (297.0, "one 2 s shift in the window"),
           "turn-schedule": (7201.0, "turning: every frame moves")}
"""Scene -> first frame time (s) and what the window holds; frames are 1 s apart, the bed primed 1 s before."""
CONFIGURATIONS = (("fields", False), ("fields", True), ("block", False), ("block", True))
DENSITIES = (2.0, 1.0, 0.5, 0.25)
MERGES = (1, 2, 5)
PAIRS = (("restless", 290.0, 302.0), ("turn-schedule", 7190.0, 7230.0), ("head-raised", 1790.0, 1840.0))
"""Scene times whose change of readings the detail levels must reproduce: a shift, a turn, the head raised."""
MOVING_FRAMES = (("restless", 301.0), ("turn-schedule", 7201.0), ("head-raised", 1801.0), ("leaves-bed", 3601.0))
TOLERANCES = (1e-2, 1e-3)
UPDATE_RANKS = (2, 16, 32, 64, 127)


class SlidingWeight(Scene):
    """The thesis's 100 mm mat with a 30 mm soft weight (4.36 kPa) that slides 30 mm from ``start_s`` to ``end_s``."""

    def __init__(self, start_s: float, end_s: float, duration_s: float):
        self.grid = MatGrid(100.0, 100.0, 2.0)
        self.start_s, self.end_s, self.duration_s = start_s, end_s, duration_s

    def _x_mm(self, t_s: float) -> float:
        return 35.0 + 30.0 * min(1.0, max(0.0, (t_s - self.start_s) / (self.end_s - self.start_s)))

    def pressure_at(self, t_s: float) -> PressureField:
        return self.grid.zeros().with_square_load(self._x_mm(t_s), 50.0, 30.0, 4.36)

    def change_box_mm(self, t0_s: float, t1_s: float):
        x0, x1 = self._x_mm(t0_s), self._x_mm(t1_s)
        return None if x0 == x1 else (min(x0, x1) - 15.0, 35.0, max(x0, x1) + 15.0, 65.0)


def run_window(bed: VirtualBed, start_s: float, cache: bool) -> dict:
    """Time FRAMES frames from ``start_s`` (bed primed at ``start_s - 1``): frame, transfer and chain seconds."""
    bed.transfer_ohm(start_s - 1.0)
    front_end = VirtualFrontEnd(bed, default_protocol(bed.layout), start_s=start_s)
    solves = bed.solves
    spent = []
    transfer = bed.transfer_ohm

    def timed(now_s):
        begin = time.perf_counter()
        z = transfer(now_s)
        spent.append(time.perf_counter() - begin)
        return z

    bed.transfer_ohm = timed
    bed.seconds = dict.fromkeys(bed.seconds, 0.0)
    frames = []
    for _ in range(FRAMES):
        if not cache:
            bed.set_scene(bed.scene)
        begin = time.perf_counter()
        front_end.acquire()
        frames.append(time.perf_counter() - begin)
    del bed.transfer_ohm
    frames, spent = np.array(frames), np.array(spent)
    solved = bed.solves - solves
    return {"frame": float(np.median(frames)), "total": float(frames.sum()), "bed": float(np.median(spent)),
            "chain": float(np.median(frames - spent)), "solves": solved,
            "stages": {k: v / solved for k, v in bed.seconds.items()} if solved else None}


def frame_rates() -> tuple[list[list], dict]:
    """Frames per second for each scene and configuration, on the bed and on the thesis's 4x4 mat."""
    cases = [(BED, name, lambda name=name: load_scene(name), start, what) for name, (start, what) in WINDOWS.items()]
    cases += [("grid-4x4", "sliding weight, still", lambda: SlidingWeight(20.0, 40.0, 60.0), 5.0, "still"),
              ("grid-4x4", "sliding weight, moving", lambda: SlidingWeight(20.0, 40.0, 60.0), 21.0,
               "sliding: every frame moves")]
    rows, results = [], {}
    for layout_name, name, make, start, what in cases:
        layout = get_layout(layout_name)
        base = None
        for solver, cache in CONFIGURATIONS:
            r = run_window(VirtualBed(layout, make(), solver=solver), start, cache)
            results[layout_name, name, solver, cache] = r
            base = base or r
            rows.append([layout_name, name, what, solver, "yes" if cache else "no (forced re-solve)",
                         f"{r['solves']}/{FRAMES}", f"{r['frame'] * 1e3:.1f}", f"{1 / r['frame']:.2f}",
                         f"{FRAMES / r['total']:.2f}", f"{base['total'] / r['total']:.1f}",
                         f"{r['bed'] * 1e3:.1f}", f"{r['chain'] * 1e3:.1f}"]
                        + ([f"{(r['stages']['scene'] + r['stages']['mechanics']) * 1e3:.0f}",
                            f"{r['stages']['transfer'] * 1e3:.0f}"] if r["stages"] else ["-", "-"]))
    return rows, results


def detail_levels() -> tuple[list[list], dict, tuple]:
    """Speed of a moving frame and error of the change of readings at each density x mechanics_merge."""
    layout = get_layout(BED)
    protocol = default_protocol(layout)
    a, b, c, d = (protocol.readings - 1).T
    solvers = {density: TransferSolver(build_fem_model(layout, density=density)) for density in DENSITIES}
    readings = {}
    for name, t0, t1 in PAIRS:
        bed = VirtualBed(layout, load_scene(name), density=DENSITIES[-1])      # its field_at and parameters
        for merge in MERGES:
            state, grids = None, []
            for t in (t0, t1):
                field = bed.field_at(t)
                field = field.coarsened(merge) if merge > 1 else field
                conductance, _, state = sheet_conductance(bed.params, field, state, bed.temperature_at(t))
                grids.append((conductance, field.pitch_mm))
            for density, solver in solvers.items():
                z0, z1 = (solver.transfer(conductance_on_model(solver.model, g, pitch)) for g, pitch in grids)
                readings[name, merge, density] = [z[c, a] - z[c, b] - z[d, a] + z[d, b] for z in (z0, z1)]
    accuracy = board_profile({}).accuracy.relative
    rows, speed, chosen = [], {}, None
    for merge in MERGES:
        for density in DENSITIES:
            bed = VirtualBed(layout, load_scene("turn-schedule"), density=density, mechanics_merge=merge)
            bed.transfer_ohm(7200.0)
            bed.seconds = dict.fromkeys(bed.seconds, 0.0)
            for t in (7201.0, 7202.0, 7203.0):
                bed.transfer_ohm(t)
            per_frame = {k: v / 3 for k, v in bed.seconds.items()}
            errors, of_reading = [], []
            for name, _, _ in PAIRS:
                ref0, ref1 = readings[name, 1, DENSITIES[0]]
                here0, here1 = readings[name, merge, density]
                change = ref1 - ref0
                error = np.sqrt(np.mean((here1 - here0 - change) ** 2))
                errors.append(error / np.sqrt(np.mean(change ** 2)))
                of_reading.append(error / np.sqrt(np.mean(ref0 ** 2)))
            frame_s = sum(per_frame.values())
            speed[density, merge] = (frame_s, max(errors))
            fits = max(of_reading) < accuracy and density != DENSITIES[0]
            if fits and (chosen is None or frame_s < speed[chosen][0]):
                chosen = (density, merge)
            rows.append([f"{density:g}", merge, "x".join(str(n) for n in bed.field_at(0.0).coarsened(merge)
                                                        .pressure_kpa.shape),
                         bed.model.system.n] + [f"{per_frame[k] * 1e3:.0f}" for k in ("scene", "mechanics", "transfer")]
                        + [f"{frame_s * 1e3:.0f}"] + [f"{e:.1%}" for e in errors] + [f"{max(of_reading):.2%}"])
    return rows, speed, chosen


def locality() -> tuple[list[list], list[list], VirtualBed, str]:
    """How much of the mat a moving frame changes, what a local update would cost against a re-solve on
    the default bed (returned), and the rank where an update stops paying."""
    layout = get_layout(BED)
    change_rows = []
    for name, t in MOVING_FRAMES:
        bed = VirtualBed(layout, load_scene(name))
        before, after = bed.field_at(t - 1.0), bed.field_at(t)
        c0, _, state = sheet_conductance(bed.params, before, None, 24.0)
        c1, _, _ = sheet_conductance(bed.params, after, state, 24.0)
        s0, s1 = (conductance_on_model(bed.model, g, after.pitch_mm) for g in (c0, c1))
        moved = np.abs(after.pressure_kpa - before.pressure_kpa) > CHANGE_TOLERANCE_KPA
        cells = [np.mean(np.abs(c1 / c0 - 1) > tol) for tol in TOLERANCES]
        elements = [int(np.sum(np.abs(s1 / s0 - 1) > tol)) for tol in TOLERANCES]
        change_rows.append([name, f"{t:g}", f"{moved.mean():.0%}"] + [f"{x:.0%}" for x in cells]
                           + [f"{e} ({e / bed.model.n_elements:.0%}): rank {2 * e}" for e in elements])
    bed = VirtualBed(layout, load_scene("supine-still"))
    field = bed.field_at(600.0)
    sigma = conductance_on_model(bed.model, sheet_conductance(bed.params, field, None, 24.0)[0], field.pitch_mm)
    block = TransferSolver(bed.model)
    full_s = median_seconds(lambda: block.transfer(sigma), 5)
    cost_rows = [["full re-solve, transfer alone (block)", f"{full_s * 1e3:.0f}"],
                 ["full re-solve, a field per electrode (fields)",
                  f"{median_seconds(lambda: solve_electrodes(bed.model, sigma), 3) * 1e3:.0f}"]]
    factor = factorise(bed.model, sigma)
    rng = np.random.default_rng(0)
    costs = []
    for rank in UPDATE_RANKS:
        columns = np.zeros((bed.model.system.n, rank))
        columns[rng.choice(bed.model.system.n, rank, replace=False), np.arange(rank)] = 1.0
        dense = rng.standard_normal((rank, rank))
        dense = dense @ dense.T + rank * np.eye(rank)
        label = (f"rank-{rank} update, at least: {rank} solves through the old factor + {rank}x{rank} Cholesky"
                 if rank != 127 else "one warm-started CG step, at least: 127 solves through the old factor")
        costs.append(median_seconds(lambda columns=columns, dense=dense: (factor.solve(columns),
                                                                          np.linalg.cholesky(dense)), 3))
        cost_rows.append([label, f"{costs[-1] * 1e3:.0f}"])
    dearer = next((i for i, cost in enumerate(costs) if cost > full_s), None)
    if dearer is None:
        crossover = f"beyond rank {UPDATE_RANKS[-1]}"
    elif dearer == 0:
        crossover = f"below rank {UPDATE_RANKS[0]}"
    else:
        rank = np.interp(full_s, costs[dearer - 1:dearer + 1], UPDATE_RANKS[dearer - 1:dearer + 1])
        crossover = f"from rank {rank:.0f} on (about {rank / 2:.0f} changed elements)"
    return change_rows, cost_rows, bed, crossover


def main() -> None:
    began, load_before = time.perf_counter(), os.getloadavg()[0]
    fps_rows, fps = frame_rates()
    detail_rows, speed, chosen = detail_levels()
    change_rows, cost_rows, default_bed, crossover = locality()
    defaults = inspect.signature(VirtualBed).parameters
    default = (defaults["density"].default, defaults["mechanics_merge"].default)
    plot(fps, speed, default)
    fps_table = table(["layout", "scene", "window", "solver", "cache", "solves", "median frame ms", "fps (median)",
                       "fps (one run)", "one-run ratio", "median transfer_ohm ms", "median chain ms",
                       "scene + mechanics ms per solve", "transfer ms per solve"],
                      fps_rows)
    detail_table = table(["density", "mechanics_merge", "mechanics cells", "FEM unknowns", "scene ms", "mechanics ms",
                          "transfer ms (block)", "moving frame ms"]
                         + [f"error {name}" for name, _, _ in PAIRS] + ["worst error, % of rms reading"],
                         detail_rows)
    change_table = table(["scene", "frame s", "cells pressed differently"]
                         + [f"cells with conductance moved > {tol:g}" for tol in TOLERANCES]
                         + [f"elements moved > {tol:g} (of {default_bed.model.n_elements})" for tol in TOLERANCES],
                         change_rows)
    cost_table = table([f"on the default bed ({default_bed.model.system.n} unknowns)", "ms"], cost_rows)
    mat = mat_parameters_for(get_layout(BED))
    spreading_mm = (mat.tension_n_per_m / mat.foundation_kpa_per_mm) ** 0.5
    verdict = (f"density {chosen[0]:g}, mechanics_merge {chosen[1]}" if chosen else "none of the levels")
    matches = chosen == default
    text = f"""# Simulator: virtual-bed frames per second, and the detail a bed needs

Command: `{COMMAND}` ({machine()}). The run took {time.perf_counter() - began:.0f} s; the machine's
one-minute load average was {load_before:.1f} at its start and {os.getloadavg()[0]:.1f} at its end on
{os.cpu_count()} cores: other work shared them, and single timings carry that noise.

A frame is `VirtualFrontEnd.acquire()`: the bed's transfer impedances at the frame's scene time
(`VirtualBed.transfer_ohm`: scene -> mat mechanics -> sheet conductance -> forward model) and the
whole-frame analogue chain on them, frames 1 s of scene time apart. Bed: {BED} ({default_bed.n_electrodes} electrodes,
{" x ".join(f"{side:g}" for side in get_layout(BED).sheet.size_mm)} mm) at VirtualBed's defaults (density {default[0]:g}, mechanics_merge {default[1]});
grid-4x4 is the thesis's 100 mm mat with a soft 30 mm weight sliding 30 mm over 20 s, for reference.

* **cache**: the bed's own; it re-solves only when the scene or the temperature changed. "no" forces a
  re-solve of every frame by putting the same scene back on the mat (`set_scene(bed.scene)`), as a
  simulator without the cache would.
* **solver**: "block" is `appliance/sim/transfer.py`, the transfer alone from one factorisation with
  the electrodes' unknowns numbered last (`VirtualBed(..., solver="block")`, the default); "fields"
  solves a field per electrode (`solve_electrodes`), as the bed did before.
* No local update is among them: none paid (next section).

Each window is {FRAMES} frames timed one by one in one run, the bed primed one frame before. "fps
(median)" is one over the median frame: where only some frames of a window move, that is a still
frame's rate. "fps (one run)" is frames over the window's total time; the ratio is of one-run rates
against the first configuration of the same scene (fields, no cache). The per-solve columns split the
bed's re-solves into the scene's field with the mechanics, and the transfer.

## Frames per second

{fps_table}

## A local update does not pay on these scenes

The liquid's volume is conserved and the membrane is slack near rest, so when a patient moves the
liquid pressure moves and the lifted membrane everywhere follows: the conductance changes on much more
of the mat than the pressure did (default detail; one frame into each movement). A triangle's
conductance enters K as a rank-2 term, so an update over k elements is of rank 2k:

{change_table}

What the alternatives cost on the default bed (medians; the update rows are lower bounds, the solves
alone, without forming or applying the update):

{cost_table}

A rank-r (Woodbury) update of the transfer needs at least r solves through the old factorisation, so
it loses to the full block re-solve {crossover}; the scenes' movements change hundreds
to tens of thousands of elements by more than 1 %, and dropping the smaller changes would not be
exact. A conjugate-gradient solve started from the previous fields with the old factor as
preconditioner costs at least a field per electrode per step, more than the whole block re-solve.
Re-solving the mechanics only where the pressure moved would miss the lift elsewhere that the table
shows, and where the pressure moved is up to half of the mat. So the bed keeps the full re-solve, made
cheaper by solving for the transfer alone, and the cache for every frame in which nothing moved.

## Detail: speed against error

Error is the relative RMS error of the change of the readings (the default protocol's
{len(default_protocol(get_layout(BED)))} readings, before the chain) between the two scene times of each
pair ({", ".join(f"{n} {t0:g} -> {t1:g} s" for n, t0, t1 in PAIRS)}), against the finest setting here
(density {DENSITIES[0]:g}, mechanics_merge 1, the scenes' own 10 mm cells): that change is what
reconstruction sees. The last column is the worst of those errors as a share of the RMS reading, to set
against the front end's stated accuracy of {board_profile({}).accuracy.relative:.1%} of a reading. Times
are per moving frame (the mean of three frames into turn-schedule's first turn, solver block).

{detail_table}

At full mechanics detail the mechanics is most of a moving frame, and the mesh's density changes the
frame's time little while it changes the error much; merging the scene's cells makes the mechanics
cheap, and merged by five it errs by more than the front end's accuracy, since the membrane's spreading
length (sqrt(T / k), {spreading_mm:.1f} mm on the bed's mat, less where a load stiffens the foundation) is
already below a 10 mm cell. The
cheapest level whose worst error stays below the front end's accuracy is **{verdict}**; VirtualBed's
defaults are density {default[0]:g}, mechanics_merge {default[1]}{" (the same)" if matches else " (NOT the same: revisit)"}.

![frames per second and detail](simulator.png)
"""
    (HERE / "simulator.md").write_text(text)
    print(text)


def plot(fps: dict, speed: dict, default: tuple) -> None:
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    scenes = [(layout, name) for layout, name, solver, cache in fps if (solver, cache) == CONFIGURATIONS[0]]
    width = 0.8 / len(CONFIGURATIONS)
    for i, (solver, cache) in enumerate(CONFIGURATIONS):
        rates = [FRAMES / fps[layout, name, solver, cache]["total"] for layout, name in scenes]
        axes[0].bar(np.arange(len(scenes)) + i * width, rates, width,
                    label=f"{solver}, {'cache' if cache else 'no cache'}")
    axes[0].set_xticks(np.arange(len(scenes)) + 0.4 - width / 2, [f"{lay}\n{n}" for lay, n in scenes], fontsize=7)
    axes[0].set_yscale("log")
    axes[0].set_ylabel("frames per second (one run)")
    axes[0].legend(fontsize=8)
    for (density, merge), (seconds, error) in speed.items():
        if density == DENSITIES[0] and merge == 1:
            continue
        axes[1].scatter(seconds * 1e3, error, marker="os^"[MERGES.index(merge)],
                        color="C3" if (density, merge) == default else "C0")
        axes[1].annotate(f"d{density:g} m{merge}", (seconds * 1e3, error), fontsize=7)
    axes[1].set_xscale("log")
    axes[1].set_yscale("log")
    axes[1].set_xlabel("moving frame ms (mechanics + transfer)")
    axes[1].set_ylabel("worst relative error of the change of readings")
    axes[1].set_title(f"{BED}: detail levels (red: default)")
    save_figure(fig, HERE / "simulator.png")


if __name__ == "__main__":
    main()
