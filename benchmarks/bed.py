"""The bed chain on real bodies: what the appliance reads of people it was never fitted to.

    python benchmarks/bed.py                 # writes benchmarks/bed.md and bed.png (about an hour)
    python benchmarks/bed.py --only chosen   # the chosen design alone (about 15 min)

Real pressure maps (PmatData experiment I: 64 x 32 sensels of about 28.5 mm, scaled to each person's
weight, `appliance/sim/recordings.py`) are laid on the virtual bed and read through the whole chain:
mat mechanics -> the front end's frames -> reconstruction -> pressure calibration, exactly as the
monitor reads them (:class:`appliance.service.monitor.Monitor` with the model and calibration the
appliance builds). Each design is calibrated on the maps of eight people (S1, S2, S3, S5, S7, S8, S9,
S10: one mid-recording frame of each of their 17 postures) and judged on three others it never saw
(S4, S6, S11, all 17 postures; none of them is in PmatData's experiment II either, whose volunteers
are experiment I's S1-S3, S5, S7-S10 and S12).

The monitor reads each held-out posture for two frames, as a patient who has just lain down: the parallel
board reads adaptively (fine drives only near the electrodes the last map found loaded), so the first frame's
fine readings are where the previous posture lay, and the second, which is judged, is settled.

A loaded spot is a connected set of 30 mm pixels where the true map, averaged over them, is at or above
32 mmHg, with a true peak of 40 mmHg or more; every design is judged on the same spots, its own map read at
each 30 mm pixel as the highest of its pixels overlapping it. A spot is seen when the map read reaches
32 mmHg within one pixel of it; its peak error is the highest pressure read there against
the true peak. Body sites are told from the spot's place along and across the body (head, shoulders,
elbows, sacrum, hips, knees, heels). A 30 degree tilt is told apart from supine when the centre of
pressure moves across the bed to the same side in the map read as in the truth.
"""

from __future__ import annotations

import appliance  # noqa: F401  (first: it pins BLAS to one thread before numpy loads)

import argparse
import dataclasses
import json
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

from appliance.calibration import MapLoad
from appliance.core.model_cache import ModelSetup, cached_model, default_setup
from appliance.core.named_layouts import get_layout
from appliance.core.pixels import pixel_grid
from appliance.core.pressure import KPA_PER_MMHG
from appliance.core.reconstruct import ReconstructionOptions
from appliance.sim.recordings import pmat_map_loads

sys.path.insert(0, str(Path(__file__).parent))
from report import machine, pyplot, table  # noqa: E402

HERE = Path(__file__).parent
PMAT = HERE.parent.parent / "shared" / "data" / "pmatdata"
TRAINING = (1, 2, 3, 5, 7, 8, 9, 10)
HELD_OUT = (4, 6, 11)
THRESHOLD_MMHG = 32.0
LOADED_MMHG = 40.0
SITES = ("head", "shoulders", "elbows", "sacrum", "hips", "knees", "heels")
SIDE_LYING = {2, 3, 4, 5, 6, 7, 13, 14}            # PmatData experiment I postures on a side or rolled
TILTS = {4: "right", 6: "left"}                     # the 30 degree wedges; 1 is supine


# ---------------------------------------------------------------------------
# Spots, sites and tilt

def loaded_spots(truth_mmhg: np.ndarray) -> list[np.ndarray]:
    """Masks of the true map's connected regions at or above 32 mmHg that peak at 40 mmHg or more."""
    labels, count = ndimage.label(np.nan_to_num(truth_mmhg) >= THRESHOLD_MMHG, structure=np.ones((3, 3)))
    masks = [labels == k for k in range(1, count + 1)]
    return [m for m in masks if truth_mmhg[m].max() >= LOADED_MMHG]


def body_site(truth_mmhg: np.ndarray, spot: np.ndarray, posture: int) -> str:
    """Where on the body a spot lies, from its place along the body (head towards x = 0) and across it."""
    i, j = np.unravel_index(np.argmax(np.where(spot, truth_mmhg, -np.inf)), spot.shape)
    loaded = np.nan_to_num(truth_mmhg) >= 5.0
    columns, rows = np.flatnonzero(loaded.any(axis=0)), np.flatnonzero(loaded.any(axis=1))
    along = (j - columns.min()) / max(columns.max() - columns.min(), 1)
    weights = np.clip(np.nan_to_num(truth_mmhg), 0, None).sum(axis=1)
    across = abs(i - np.average(np.arange(len(weights)), weights=weights)) / max((rows.max() - rows.min()) / 2, 1)
    if along < 0.14:
        return "head"
    if along >= 0.86:
        return "heels"
    if along >= 0.62:
        return "knees"
    if 0.25 <= along < 0.52 and across > 0.45 and posture not in SIDE_LYING:
        return "elbows"
    if along < 0.36:
        return "shoulders"
    return "hips" if posture in SIDE_LYING else "sacrum"


@dataclass(frozen=True)
class Spot:
    subject: int
    posture: int
    site: str
    true_mmhg: float
    read_mmhg: float

    @property
    def seen(self) -> bool:
        return self.read_mmhg >= THRESHOLD_MMHG

    @property
    def error(self) -> float:
        return (self.read_mmhg - self.true_mmhg) / self.true_mmhg


def spots_of(truth_mmhg: np.ndarray, read_mmhg: np.ndarray, subject: int, posture: int) -> list[Spot]:
    """Every loaded spot of the true map with the peak read within one pixel of it."""
    out = []
    for spot in loaded_spots(truth_mmhg):
        near = ndimage.binary_dilation(spot, structure=np.ones((3, 3)))
        out.append(Spot(subject, posture, body_site(truth_mmhg, spot, posture), float(truth_mmhg[spot].max()),
                        float(np.nanmax(read_mmhg[near]))))
    return out


TRUTH_PIXELS = (30, 64)
"""Every design is judged on the same spots: the truth on 30 mm pixels (29.7 x 30 mm), whatever the design's
own pixels; a design's map is read at each of these pixels as the highest of its own pixels overlapping it."""


def on_pixels(read: np.ndarray, grid, shape: tuple[int, int]) -> np.ndarray:
    """``read`` (on ``grid``) at each pixel of a ``shape`` grid over the same sheet: the highest value of the
    pixels of ``grid`` that overlap it."""
    def spans(n_from, n_to):
        edges_to = np.linspace(0.0, 1.0, n_to + 1)
        first = np.floor(edges_to[:-1] * n_from + 1e-9).astype(int)
        last = np.ceil(edges_to[1:] * n_from - 1e-9).astype(int)
        return list(zip(first, np.maximum(last, first + 1)))

    rows, cols = spans(grid.rows, shape[0]), spans(grid.cols, shape[1])
    values = np.nan_to_num(read, nan=-np.inf)
    return np.array([[values[r0:r1, c0:c1].max() for c0, c1 in cols] for r0, r1 in rows])


def centre_across(mmhg: np.ndarray) -> float:
    """The centre of pressure across the bed (rows), pixels."""
    weights = np.clip(np.nan_to_num(mmhg), 0, None).sum(axis=1)
    return float(np.average(np.arange(len(weights)), weights=weights))


def tilts_told_apart(maps: dict) -> tuple[int, int]:
    """(told apart, tried): for each held-out person and 30 degree tilt, whether the map read moves the
    centre of pressure across the bed to the side the truth moves it. ``maps[(subject, posture)]`` is
    (truth, read) in mmHg."""
    told = tried = 0
    for (subject, posture), (truth, read) in maps.items():
        if posture not in TILTS or (subject, 1) not in maps:
            continue
        truth_supine, read_supine = maps[(subject, 1)]
        tried += 1
        told += np.sign(centre_across(truth) - centre_across(truth_supine)) == \
            np.sign(centre_across(read) - centre_across(read_supine))
    return told, tried


def summary(spots: list[Spot]) -> dict:
    if not spots:
        return {"spots": 0, "seen": float("nan"), "median_abs_error": float("nan"), "median_error": float("nan")}
    errors = np.array([s.error for s in spots])
    return {"spots": len(spots), "seen": float(np.mean([s.seen for s in spots])),
            "median_abs_error": float(np.median(np.abs(errors))), "median_error": float(np.median(errors)),
            "true_median_mmhg": float(np.median([s.true_mmhg for s in spots])),
            "read_median_mmhg": float(np.median([s.read_mmhg for s in spots]))}


# ---------------------------------------------------------------------------
# The chain

@dataclass(frozen=True)
class Mat:
    """What the front end reads: a layout, its mechanics and its protocol."""

    layout: str
    stiffness_kpa_per_mm: float | None = None          # None: the appliance's mat for the layout
    protocol: str = "default"                          # or "local": every adjacent pair measured
    board: str = "default"                             # or "serial": the reference board's chain, at any size

    def protocol_of(self, layout):
        from appliance.core.protocols import default_protocol, protocol_for

        return default_protocol(layout) if self.protocol == "default" else protocol_for(layout, self.protocol)

    def source(self, seed: int = 0):
        from appliance.drivers.profile import board_profile
        from appliance.service.virtual_bed import VirtualBedSource
        from appliance.sim.bed import mat_parameters_for
        from appliance.sim.frontend import VIRTUAL_MAT_BOARD
        from appliance.sim.loads import empty_mat

        layout = get_layout(self.layout)
        params = mat_parameters_for(layout)
        if self.stiffness_kpa_per_mm is not None:
            params = dataclasses.replace(params, foundation_kpa_per_mm=self.stiffness_kpa_per_mm)
        profile = None if self.board == "default" else board_profile(VIRTUAL_MAT_BOARD)
        return VirtualBedSource(layout, empty_mat(layout), self.protocol_of(layout), seed=seed, params=params,
                                profile=profile)


class RecordedMat:
    """A mat's frames of each load, simulated once and played to every reconstruction of the same mat:
    ``place(load)`` and ``acquire()`` as the calibration procedures and the monitor use them."""

    def __init__(self, mat: Mat):
        self.mat = mat
        self._source = self.mat.source()
        self._frames: dict = {}
        self._placed = None
        self._last = None

    @property
    def adaptive(self) -> bool:
        return self._source.adaptive

    def _key(self, load):
        return None if load is None else (load.name if isinstance(load, MapLoad) else dataclasses.astuple(load))

    def place(self, load) -> None:
        self._placed = load

    def acquire(self, loaded=None):
        """The placed load's frame; with ``loaded``, the drives an adaptive board skips keep the last
        frame's readings, as the virtual front end keeps them."""
        from appliance.drivers.scan import Flag

        key = self._key(self._placed)
        if key not in self._frames:
            self._source.place(self._placed)
            self._frames[key] = self._source.acquire()
        frame = self._frames[key]
        if loaded is not None and self._last is not None:
            plan = self._source.front_end.plan
            held = ~np.isin(plan.protocol.drive_index, plan.drives_for(loaded))
            frame = dataclasses.replace(frame, volts=np.where(held, self._last.volts, frame.volts),
                                        flags=np.where(held, self._last.flags | Flag.HELD, frame.flags))
        self._last = frame
        return frame

    def empty_reference(self):
        self.place(None)
        return self.acquire()


@dataclass(frozen=True)
class Design:
    """One candidate: a mat, and how its frames are reconstructed and calibrated."""

    name: str
    mat: Mat
    algorithm: str | None = None
    options: ReconstructionOptions | None = None        # all of them at once, instead of the appliance's
    density: float | None = None
    pixels: tuple[int, int] | None = None
    calibration: str = "maps"                           # or "weights"
    note: str = ""

    def setup(self) -> ModelSetup:
        layout = get_layout(self.mat.layout)
        setup = default_setup(layout, self.mat.protocol_of(layout))
        if self.options:
            setup = dataclasses.replace(setup, options=self.options)
        if self.algorithm:
            setup = dataclasses.replace(setup, options=dataclasses.replace(setup.options, algorithm=self.algorithm))
        if self.density:
            setup = dataclasses.replace(setup, density=self.density)
        if self.pixels:
            setup = dataclasses.replace(setup, pixels=self.pixels)
        return setup


@dataclass
class Outcome:
    design: Design
    spots: list
    tilts: tuple[int, int]
    readings: int
    pixel_mm: tuple[float, float]
    build_s: float
    build_peak_mb: float
    frame_ms: float
    maps: dict
    grid: object


def calibrate(design: Design, model, recorded: RecordedMat):
    from appliance.calibration import calibration_loads, pressure_calibration

    loads = pmat_map_loads(PMAT, TRAINING) if design.calibration == "maps" else calibration_loads(model.setup.layout)
    return pressure_calibration(recorded.acquire, recorded.place, model, loads)


def read_held_out(model, calibration, recorded: RecordedMat, subjects=HELD_OUT) -> tuple[list, dict, float]:
    """Every held-out posture through the monitor: spots, {(subject, posture): (truth, read)} in mmHg, and
    the monitor's median CPU ms a frame (reconstruction and calibration; the simulation is not counted)."""
    from appliance.service.monitor import Monitor

    monitor = Monitor(recorded.acquire, model, calibration, adaptive=recorded.adaptive)
    monitor.take_reference(recorded.empty_reference())
    grid = model.reconstructor.grid
    truth_grid = pixel_grid(model.setup.layout, *TRUTH_PIXELS)
    spots, maps, seconds = [], {}, []
    for subject in subjects:
        for load in pmat_map_loads(PMAT, [subject]):
            posture = int(load.name.split("/")[1].split("#")[0])
            recorded.place(load)
            monitor.next_map()          # the frame the person lay down in: fine drives where the last lay
            start = time.process_time()
            pressure = monitor.next_map()                       # settled: fine drives where this one lies
            seconds.append(time.process_time() - start)
            truth = load.pixel_pressure(truth_grid) / KPA_PER_MMHG
            read = on_pixels(pressure.pressure_kpa / KPA_PER_MMHG, grid, TRUTH_PIXELS)
            maps[(subject, posture)] = (truth, read)
            spots += spots_of(truth, read, subject, posture)
    return spots, maps, float(np.median(seconds)) * 1e3


def build_cost(design: Design) -> tuple[float, float]:
    """(seconds, peak MB) of building the design's reconstruction model cold, in a process of its own."""
    out = subprocess.run([sys.executable, __file__, "--build", design.name], capture_output=True, text=True,
                         check=True)
    cost = json.loads(out.stdout.strip().splitlines()[-1])
    return cost["seconds"], cost["peak_mb"]


def _build_only(name: str) -> None:
    from appliance.core.model_cache import build_model

    design = next(d for d in DESIGNS if d.name == name)
    start = time.perf_counter()
    build_model(design.setup())
    print(json.dumps({"seconds": time.perf_counter() - start, "peak_mb": _peak_mb()}))


def _peak_mb() -> float:
    """This process's peak resident memory since it started (VmHWM). Not getrusage's ru_maxrss, which a
    process started by another carries over from its parent's, however large that was."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmHWM in /proc/self/status")


def run(design: Design, recorded: RecordedMat, cache_dir: Path) -> Outcome:
    setup = design.setup()
    build_s, peak_mb = build_cost(design)
    model, _ = cached_model(setup, cache_dir)
    calibration = calibrate(design, model, recorded)
    spots, maps, frame_ms = read_held_out(model, calibration, recorded)
    grid = model.reconstructor.grid
    return Outcome(design, spots, tilts_told_apart(maps), len(setup.protocol), grid.pixel_mm, build_s, peak_mb,
                   frame_ms, maps, pixel_grid(setup.layout, *TRUTH_PIXELS))


# ---------------------------------------------------------------------------
# Nights: the alert layer fed the true maps and the maps read

NIGHTS = {
    "supine, never turned": [(1, 8.0)],
    "turned every 2 h": [(1, 2.0), (4, 2.0), (1, 2.0), (6, 2.0)],
    "right side, 6 h": [(2, 6.0)],
    "head of bed 45 degrees, 6 h": [(16, 6.0)],
    "left fetal, 6 h": [(14, 6.0)],
}
MATCH_S = 3600.0


def night_alarms(sequence: list, maps: dict, subject: int, which: int, grid) -> list[tuple[float, str]]:
    """(time, site) of each pressure alarm the alert layer raises over a night of held postures, one map a
    minute; ``which`` 0 plays the true maps, 1 the maps read."""
    from appliance.alerts.pipeline import AlertPipeline
    from appliance.core.pressure_map import PressureMap, loaded_regions

    pipeline, t, raised = AlertPipeline(grid), 0.0, []
    for posture, hours in sequence:
        kpa = np.nan_to_num(maps[(subject, posture)][which]) * KPA_PER_MMHG
        pressure = PressureMap(0.0, kpa, loaded_regions(kpa, grid), None, 0)
        for _ in range(int(hours * 60)):
            alerts = pipeline.update(dataclasses.replace(pressure, time_s=t))
            raised += [(t, e.key.split(":")[1]) for e in alerts.alarm_events
                       if e.kind == "raised" and e.key.startswith("pressure:")]
            t += 60.0
    return raised


def nights(maps: dict, grid) -> dict:
    """Per night: site alarms of the true maps, how many the maps read missed (no alarm at that site within
    an hour), and alarms read with no true one near them."""
    out = {}
    for name, sequence in NIGHTS.items():
        true = read = missed = extra = 0
        for subject in HELD_OUT:
            truth_alarms = night_alarms(sequence, maps, subject, 0, grid)
            read_alarms = night_alarms(sequence, maps, subject, 1, grid)
            near = lambda a, others: any(site == a[1] and abs(t - a[0]) <= MATCH_S for t, site in others)  # noqa
            true += len(truth_alarms)
            read += len(read_alarms)
            missed += sum(not near(a, read_alarms) for a in truth_alarms)
            extra += sum(not near(a, truth_alarms) for a in read_alarms)
        out[name] = {"true": true, "read": read, "missed": missed, "extra": extra}
    return out


# ---------------------------------------------------------------------------
# The designs tried

THESIS_STIFFNESS = 1.183       # the thesis sensor's foundation as first fitted to its load tests
TODAY = Mat("grid-8x16", THESIS_STIFFNESS, "local", "serial")
M8, M12, M16, M20 = Mat("grid-8x16"), Mat("grid-12x24"), Mat("grid-16x32"), Mat("grid-20x40")
CHOSEN = "grid-16x32"
DESIGNS = (
    Design("before", TODAY, options=ReconstructionOptions(), density=1.0, pixels=(16, 34), calibration="weights",
           note="the mat before: 125 mm pitch, the thesis's mat, GREIT on 56 mm pixels, weights"),
    Design("grid-8x16", M8, note="125 mm pitch, the bed mat"),
    Design("grid-12x24", M12, note="80 mm pitch"),
    Design("16x32 thesis mat", Mat("grid-16x32", THESIS_STIFFNESS), note="60 mm pitch on the thesis's mat"),
    Design(CHOSEN, M16, note="60 mm pitch, the bed mat: chosen"),
    Design("16x32 weights", M16, calibration="weights", note="calibrated with weights, not maps"),
    Design("16x32 GREIT", M16, algorithm="greit", note="GREIT instead of Gauss-Newton"),
    Design("16x32 rows, serial chain", Mat("grid-16x32", board="serial"),
           note="read through the reference board's chain, to compare with the next"),
    Design("16x32 all pairs, serial chain", Mat("grid-16x32", protocol="local", board="serial"),
           note="every adjacent pair measured, not only those along the rows"),
    Design("16x32 fine mesh", M16, density=1.0, note="reconstruction mesh at full density"),
    Design("16x32 20 mm", M16, pixels=(45, 95), note="20 mm pixels"),
    Design("grid-20x40", M20, note="48 mm pitch"),
)


# ---------------------------------------------------------------------------
# Report

def percent(x: float) -> str:
    return "-" if not np.isfinite(x) else f"{100 * x:.0f} %"


def design_row(o: Outcome) -> list:
    layout = get_layout(o.design.mat.layout)
    rows, cols = layout.grid_shape
    width, height = layout.sheet.size_mm
    s = summary(o.spots)
    return [o.design.name, o.design.note, layout.n_electrodes, f"{height / (rows - 1):.0f} x {width / (cols - 1):.0f}",
            o.readings, f"{o.pixel_mm[0]:.0f}", percent(s["seen"]), percent(s["median_abs_error"]),
            percent(s["median_error"]), f"{o.tilts[0]}/{o.tilts[1]}", f"{o.build_s:.0f}", f"{o.build_peak_mb:.0f}",
            f"{o.frame_ms:.0f}"]


def site_rows(spots: list) -> list:
    rows = []
    for site in SITES:
        s = summary([x for x in spots if x.site == site])
        if s["spots"]:
            rows.append([site, s["spots"], percent(s["seen"]), percent(s["median_abs_error"]),
                         f"{s['true_median_mmhg']:.0f}", f"{s['read_median_mmhg']:.0f}"])
    s = summary(spots)
    rows.append(["all", s["spots"], percent(s["seen"]), percent(s["median_abs_error"]),
                 f"{s['true_median_mmhg']:.0f}", f"{s['read_median_mmhg']:.0f}"])
    return rows


def plot(outcomes: list, path: Path) -> None:
    plt = pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.8))
    for o in outcomes:
        s = summary(o.spots)
        left.scatter(o.readings, 100 * s["median_abs_error"], color="C3" if o.design.name == CHOSEN else "C0")
        left.annotate(o.design.name, (o.readings, 100 * s["median_abs_error"]), fontsize=7,
                      xytext=(4, 3), textcoords="offset points")
        right.scatter(o.build_s, 100 * s["seen"], color="C3" if o.design.name == CHOSEN else "C0")
        right.annotate(o.design.name, (o.build_s, 100 * s["seen"]), fontsize=7, xytext=(4, 3),
                       textcoords="offset points")
    left.set(xscale="log", xlabel="readings a frame", ylabel="median |peak error| of held-out people, %")
    left.axhline(25, color="grey", lw=0.8, ls="--")
    right.set(xlabel="cold model build, s", ylabel="loaded spots seen (>= 32 mmHg), %")
    right.axhline(95, color="grey", lw=0.8, ls="--")
    from report import save_figure

    save_figure(fig, path, "Bed designs on people left out of every fit")


def chosen_maps_figure(outcome: Outcome, path: Path) -> None:
    plt = pyplot()
    picks = [(HELD_OUT[0], 1), (HELD_OUT[0], 6), (HELD_OUT[1], 13), (HELD_OUT[2], 17)]
    fig, axes = plt.subplots(len(picks), 2, figsize=(10, 2.3 * len(picks)))
    for row, key in zip(axes, picks):
        truth, read = outcome.maps[key]
        for ax, image, label in zip(row, (truth, read), ("true", "read")):
            ax.imshow(image, vmin=0, vmax=100, cmap="turbo")
            ax.set(title=f"S{key[0]} posture {key[1]}: {label}, peak {np.nanmax(image):.0f} mmHg", xticks=[],
                   yticks=[])
    from report import save_figure

    save_figure(fig, path, f"{CHOSEN}: true and read maps of held-out people (0-100 mmHg)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", help="one design by name (\"chosen\" for the chosen one)")
    parser.add_argument("--build", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.build:
        _build_only(args.build)
        return
    import tempfile

    names = [CHOSEN if args.only == "chosen" else args.only] if args.only else [d.name for d in DESIGNS]
    designs = [d for d in DESIGNS if d.name in names]
    if not designs:
        raise SystemExit(f"no design named {args.only!r}: {', '.join(d.name for d in DESIGNS)}")
    recorded = {}
    outcomes = []
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as cache:
        for design in designs:
            print(f"{design.name}: {design.note}", flush=True)
            if design.mat not in recorded:
                recorded[design.mat] = RecordedMat(design.mat)
            mat = recorded[design.mat]
            outcomes.append(run(design, mat, Path(cache)))
            s = summary(outcomes[-1].spots)
            print(f"  {s['spots']} spots, {percent(s['seen'])} seen, median |peak error| "
                  f"{percent(s['median_abs_error'])}", flush=True)
    write_report(outcomes, time.perf_counter() - start, " ".join(sys.argv[1:]))


def write_report(outcomes: list, seconds: float, arguments: str) -> None:
    command = "python benchmarks/bed.py" + (f" {arguments}" if arguments else "")
    chosen = next((o for o in outcomes if o.design.name == CHOSEN), outcomes[0])
    lines = [
        "# The bed chain on real bodies",
        "",
        f"Made by `{command}` on {machine()}; {seconds / 60:.0f} min.",
        "",
        __doc__.split("\n\n", 2)[2].strip(),
        "",
        "## Every design tried",
        "",
        "Pitch is between electrode centres (across x along the bed). Readings a frame are what the front end "
        "takes; build is the reconstruction model's cold build in a process of its own (seconds and peak resident "
        "memory); frame is the monitor's CPU time per frame on one core (reconstruction and pressure "
        "calibration, median over the held-out maps), the simulation not counted.",
        "",
        table(["design", "what", "electrodes", "pitch mm", "readings", "pixel mm", "spots seen", "median |peak "
               "error|", "median error", "tilts told", "build s", "build MB", "frame ms"],
              [design_row(o) for o in outcomes]),
        "",
        f"## {chosen.design.name} per body site",
        "",
        table(["site", "spots", "seen (>= 32 mmHg)", "median |peak error|", "true median mmHg",
               "read median mmHg"], site_rows(chosen.spots)),
        "",
        f"Tilts told apart from supine: {chosen.tilts[0]} of {chosen.tilts[1]} (30 degrees right and left, each "
        "held-out person).",
        "",
        "## Nights",
        "",
        "Each held-out person's postures held for hours, one map a minute, through the alert layer "
        "(`appliance.alerts.pipeline`, default settings, on the 30 mm pixels): fed the true maps, and fed the "
        "maps read. A true site alarm is missed when the maps read raise none at that site within an hour of it.",
        "",
        table(["design", "night (each of " + ", ".join(f"S{s}" for s in HELD_OUT) + ")", "site alarms, true maps",
               "maps read", "missed", "read, none true"],
              [[o.design.name, name, n["true"], n["read"], n["missed"], n["extra"]]
               for o in outcomes if o.design.name in ("before", CHOSEN)
               for name, n in nights(o.maps, o.grid).items()]),
        "",
        "![designs](bed.png)",
        "",
        "![maps](bed_maps.png)",
        "",
    ]
    (HERE / "bed.md").write_text("\n".join(lines))
    plot(outcomes, HERE / "bed.png")
    if chosen.maps:
        chosen_maps_figure(chosen, HERE / "bed_maps.png")


if __name__ == "__main__":
    main()
