"""End-to-end pressure accuracy: virtual bed -> front end -> reconstruction -> calibration -> kPa map.

    python benchmarks/pressure.py            # writes benchmarks/pressure.md and pressure.png
    python benchmarks/pressure.py --quick    # fewer positions, greit only on the bed (a few minutes)

Two parts. On grid-4x4 (the thesis's 100 mm mat) single flat square loads are put
at random places (fixed seed, not the calibration's places) and read back through
each reconstruction algorithm, calibrated on the same virtual bed with the default
loads (``calibration_loads``): peak, centre (``peak_region``), map RMSE against the
load's pixel pressure, loaded area and the time per frame. On the bed (grid-8x16,
1900 x 900 mm, 128 electrodes) the scene library's frames are read the same way and
compared with the true pressure field averaged into the image's pixels.
"""

from __future__ import annotations

import appliance  # noqa: F401  (first: it pins BLAS to one thread before numpy loads)

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from appliance.calibration import Load, calibration_loads, pressure_calibration
from appliance.core.model_cache import ModelSetup, cached_model, default_cache_dir
from appliance.core.named_layouts import get_layout
from appliance.core.pressure_map import HIGH_PRESSURE_KPA, loaded_area_cm2, loaded_regions, peak_region
from appliance.core.protocols import default_protocol
from appliance.core.reconstruct import ReconstructionOptions
from appliance.sim.bed import VirtualBed
from appliance.sim.frontend import VirtualFrontEnd
from appliance.sim.loads import empty_mat, placer
from appliance.sim.scenes import builtin_scenes, load_scene

sys.path.insert(0, str(Path(__file__).parent))
from report import machine, pyplot, save_figure, table  # noqa: E402

HERE = Path(__file__).parent
COMMAND = "python benchmarks/pressure.py"
ALGORITHMS = ("greit", "gn-laplace", "gn-noser", "gn-tikhonov", "backprojection")
AREAS_CM2 = (4, 9, 16, 25)
MUST_HOLD_AREAS = (9, 16, 25)
POSITIONS = 20                   # per area; medians over 12 were too noisy against the 3 mm limit
SEED = 2024                      # the calibration's front end uses seed 1 and its own places
PEAK_LIMIT, CENTRE_LIMIT_MM = 0.20, 3.0
BED_ALGORITHMS = ("greit", "gn-laplace")
SCENE_FRAMES = 5
FOUND_WITHIN_MM = 100.0
LUMPY_SHARE = 0.75               # a half-max side below this share of the true side: the image broke into lumps


def iterate_for(algorithm: str) -> str | None:
    """The calibration's ``iterate``: the product's default (``affordable_iterate``), except that
    backprojection cannot iterate and must be asked for ``never`` on a mat whose default is ``always``."""
    return "never" if algorithm == "backprojection" else None


# ----------------------------------------------------------------------------------------------------------
# helpers


def pixel_average(field, grid) -> np.ndarray:
    """The true field (10 mm cells) averaged into ``grid``'s pixels, by the share of each cell a pixel covers."""
    def shares(n_pixels, size, n_cells, pitch):
        edges = np.arange(n_pixels + 1) * size
        cells = np.arange(n_cells + 1) * pitch
        overlap = np.clip(np.minimum(edges[1:, None], cells[None, 1:]) - np.maximum(edges[:-1, None], cells[None, :-1]),
                          0, None)
        return overlap / size

    rows, cols = field.pressure_kpa.shape
    w, h = grid.pixel_mm
    ay = shares(grid.rows, h, rows, field.pitch_mm)
    ax = shares(grid.cols, w, cols, field.pitch_mm)
    return ay @ field.pressure_kpa @ ax.T


def rmse(kpa: np.ndarray, truth: np.ndarray, grid) -> float:
    inside = grid.inside & np.isfinite(kpa)
    return float(np.sqrt(np.mean((kpa[inside] - truth[inside]) ** 2)))


def match_regions(true_regions, found_regions) -> list[float]:
    """For each true region the distance (mm) to the nearest found region's centre (inf if none was found)."""
    found = np.array([(r.x_mm, r.y_mm) for r in found_regions]).reshape(-1, 2)
    if not len(found):
        return [float("inf")] * len(true_regions)
    return [float(np.hypot(*(found - (r.x_mm, r.y_mm)).T).min()) for r in true_regions]


def half_max_side_mm(kpa: np.ndarray, grid) -> float:
    """Side of the square with the area of the peak's region at half the map's peak: the image's width."""
    region = peak_region(kpa, grid, share=0.5)
    return float(np.sqrt(region.area_cm2) * 10) if region else float("nan")


def p90(values) -> float:
    return float(np.percentile(values, 90))


def fmt(value, digits=1) -> str:
    return "-" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


class PeakRecorder:
    """``model`` as ``pressure_calibration`` uses it, noting each image's peak change (max of -image)."""

    def __init__(self, model):
        self.model, self.setup, self.reconstructor, self.peaks = model, model.setup, model.reconstructor, []

    def reconstruct(self, *args, **kwargs):
        image, info = self.model.reconstruct(*args, **kwargs)
        self.peaks.append(float(np.nanmax(-image)))
        return image, info


def calibrate(model, bed, protocol, layout, iterate=None, peaks=None):
    """``pressure_calibration`` on ``bed`` with the default loads and ``placer``; the calibration, its seconds
    and any error. The frames are then read with the calibration's own ``iterate`` (``notes["iterate"]``).
    ``peaks``, if a list, gets (load pressure kPa, peak change of its one image) per calibration load."""
    front = VirtualFrontEnd(bed, protocol, seed=1)
    loads = calibration_loads(layout)
    recorder = PeakRecorder(model)
    start = time.perf_counter()
    try:
        calibration = pressure_calibration(front.acquire, placer(bed), recorder, loads, iterate=iterate)
    except Exception as exc:  # noqa: BLE001  (reported, not hidden)
        return None, time.perf_counter() - start, f"{type(exc).__name__}: {exc}"
    if peaks is not None:
        peaks += [(load.pressure_kpa, peak) for load, peak in zip(loads, recorder.peaks)]
    return calibration, time.perf_counter() - start, None


# ----------------------------------------------------------------------------------------------------------
# 1. grid-4x4, single square loads


def single_load_frames(bed, protocol, positions: int):
    """The loads (fixed seed, anywhere on the mat) and their frames, with the empty mat's frame: acquired
    once and read by every algorithm."""
    front = VirtualFrontEnd(bed, protocol, seed=SEED)
    place = placer(bed)
    place(None)
    reference = front.acquire().volts
    cases = []
    for area in AREAS_CM2:
        rng = np.random.default_rng(SEED + area)
        side = 10 * np.sqrt(area)
        for _ in range(positions):
            x, y = rng.uniform(side / 2, 100 - side / 2, 2)
            load = Load(float(x), float(y), float(side), float(rng.uniform(2, 20)))
            place(load)
            cases.append((area, load, front.acquire().volts))
    place(None)
    return reference, cases


def read_single_loads(model, calibration, reference, cases, iterate):
    """Per case: peak error, centre error (mm), RMSE (kPa), area error (cm2), half-max side (mm), seconds."""
    grid = model.reconstructor.grid
    out = []
    for area, load, volts in cases:
        start = time.perf_counter()
        image, _ = model.reconstruct(volts, reference, iterate=iterate)
        seconds = time.perf_counter() - start
        kpa = calibration.pressure_kpa(image)
        truth = load.pixel_pressure(grid)
        peak = float(np.nanmax(kpa))
        region = peak_region(kpa, grid)
        centre = np.hypot(region.x_mm - load.x_mm, region.y_mm - load.y_mm) if region else float("inf")
        area_error = loaded_area_cm2(kpa, grid, 0.5 * load.pressure_kpa) - area
        out.append(dict(area=area, peak=peak / load.pressure_kpa - 1, centre=float(centre),
                        rmse=rmse(kpa, truth, grid), area_error=area_error,
                        width=half_max_side_mm(kpa, grid), seconds=seconds, kpa=kpa, load=load))
    return out


def single_load_part(positions: int, algorithms, log):
    layout = get_layout("grid-4x4")
    protocol = default_protocol(layout)
    bed = VirtualBed(layout, empty_mat(layout))
    reference, cases = single_load_frames(bed, protocol, positions)
    results, notes, examples = {}, {}, {}
    for algorithm in algorithms:
        start = time.perf_counter()
        model, hit = cached_model(ModelSetup(layout, protocol, ReconstructionOptions(algorithm)), default_cache_dir())
        model_s = time.perf_counter() - start
        calibration, calibration_s, error = calibrate(model, bed, protocol, layout, iterate_for(algorithm))
        if calibration is None:
            notes[algorithm] = error
            log(f"grid-4x4 {algorithm}: calibration failed: {error}")
            continue
        iterate = calibration.notes["iterate"]
        rows = read_single_loads(model, calibration, reference, cases, iterate)
        results[algorithm] = dict(rows=rows, calibration_s=calibration_s, model_s=model_s, cached=hit,
                                  iterate=iterate)
        examples[algorithm] = (model.reconstructor.grid, rows)
        log(f"grid-4x4 {algorithm}: model {model_s:.1f} s ({'cached' if hit else 'built'}), calibration "
            f"{calibration_s:.0f} s, {len(rows)} loads read")
    return results, notes, examples


def single_load_tables(results):
    headers = ["algorithm", "iterate", "area cm2", "loads", "median abs peak err %", "p90 abs peak err %",
               "median centre err mm", "p90 centre err mm", "median RMSE kPa", "median area err cm2 (>= p/2)",
               "median half-max side mm", "median ms/frame", "calibration s", "must-hold"]
    rows, verdicts = [], {}
    for algorithm, result in results.items():
        for area in AREAS_CM2:
            group = [r for r in result["rows"] if r["area"] == area]
            peak = np.abs([r["peak"] for r in group]) * 100
            centre = np.array([r["centre"] for r in group])
            if area in MUST_HOLD_AREAS:
                ok = np.median(peak) <= PEAK_LIMIT * 100 and np.median(centre) <= CENTRE_LIMIT_MM
                verdicts[algorithm, area] = ok
                verdict = "PASS" if ok else "FAIL"
            else:
                verdict = "n/a (blur: see below)"
            rows.append([algorithm, result["iterate"], area, len(group), fmt(np.median(peak)), fmt(p90(peak)),
                         fmt(np.median(centre)), fmt(p90(centre)), fmt(np.median([r["rmse"] for r in group]), 2),
                         fmt(np.median([r["area_error"] for r in group])),
                         fmt(np.median([r["width"] for r in group])),
                         fmt(1e3 * np.median([r["seconds"] for r in group])), fmt(result["calibration_s"], 0),
                         verdict])
    return table(headers, rows), verdicts


def small_load_table(results):
    """Each area: signed peak error, the image's width and how much of the load's force the map keeps."""
    headers = ["algorithm", "area cm2", "true side mm", "median half-max side mm", "median signed peak err %",
               "median map force / true force (30 % footprint)", "half-max side"]
    rows = []
    for algorithm, result in results.items():
        for area in AREAS_CM2:
            group = [r for r in result["rows"] if r["area"] == area]
            width = np.median([r["width"] for r in group])
            rows.append([algorithm, area, fmt(10 * np.sqrt(area), 0), fmt(width),
                         fmt(100 * np.median([r["peak"] for r in group])),
                         fmt(np.nanmedian([r["force"] for r in group]), 2),
                         "lumps: not a width" if lumpy(width, area) else "width"])
    return table(headers, rows)


def lumpy(width_mm: float, area_cm2: float) -> bool:
    """A half-max side much smaller than the load's side: the image broke into lumps and the peak's
    region at half maximum is one lump, not the image's width."""
    return not np.isfinite(width_mm) or width_mm < LUMPY_SHARE * 10 * np.sqrt(area_cm2)


def group_median(result, area, key, scale=1.0) -> float:
    return float(np.median([r[key] for r in result["rows"] if r["area"] == area]) * scale)


def blur_notes(single) -> tuple[str, str]:
    """The 4 cm2 loads per algorithm, from the measured half-max side and peak error; and where the half-max
    measure broke down (any area)."""
    side = 10 * np.sqrt(4)
    lines = []
    for algorithm, result in single.items():
        width = group_median(result, 4, "width")
        peak = group_median(result, 4, "peak", 100)
        force = group_median(result, 4, "force")
        if lumpy(width, 4):
            lines.append(f"* {algorithm}: half-max side {fmt(width)} mm against the load's {side:.0f} mm: the image "
                         f"broke into lumps, so the half-max side is not its width and the area ratio does not apply; "
                         f"peak {peak:+.0f} % (median), 30 % footprint holds {force:.2f} of the force.\n")
            continue
        if width <= side:
            lines.append(f"* {algorithm}: imaged {width:.1f} mm at half maximum, no wider than the load's {side:.0f} mm: "
                         f"the area ratio does not explain its peak ({peak:+.0f} %, median); the 30 % footprint "
                         f"holds {force:.2f} of its force.\n")
            continue
        expected = 100 * ((side / width) ** 2 - 1)
        verdict = ("about what the area ratio predicts (within 15 points)" if abs(peak - expected) <= 15 else
                   "lower than the area ratio alone predicts" if peak < expected else
                   "higher than the area ratio predicts")
        lines.append(f"* {algorithm}: imaged {width:.1f} mm wide at half maximum against the load's {side:.0f} mm "
                     f"({width / side:.2f} x); spread over that width the peak should read about "
                     f"({side:.0f}/{width:.1f})^2 - 1 = {expected:+.0f} %, measured {peak:+.0f} % (median): {verdict}; "
                     f"the 30 % footprint holds {force:.2f} of its force.\n")
    broken = [(a, area, group_median(res, area, "width")) for a, res in single.items() for area in AREAS_CM2
              if lumpy(group_median(res, area, "width"), area)]
    if broken:
        lumps = ("Where the half-max measure breaks down (median half-max side below "
                 f"{LUMPY_SHARE:.0%} of the true side: the image broke into lumps and the peak's half-max region is "
                 "one lump): " + "; ".join(f"{a} {area} cm2 ({fmt(w)} mm against {10 * np.sqrt(area):.0f} mm)"
                                           for a, area, w in broken)
                 + ". Those rows' half-max side, and any width read from it, are not the image's width.\n")
    else:
        lumps = "No image broke into lumps: every median half-max side is at least " \
                f"{LUMPY_SHARE:.0%} of its load's side.\n"
    return "".join(lines), lumps


def curve_note(algorithm, curve, peaks=None) -> str:
    """The bed calibration's knots, the calibration loads' peak changes per pressure (``peaks``: (kPa,
    change) pairs), and how far apart 5 and 20 kPa lie on the curve."""
    knots = ", ".join(f"{c:.3g} -> {k:.1f}" for c, k in zip(curve.change, curve.pressure))
    line = f"* **{algorithm}** curve (change -> kPa), {len(curve.change)} knots: {knots}.\n"
    if peaks:
        pressures = sorted({p for p, _ in peaks})
        medians = {p: float(np.median([c for q, c in peaks if q == p])) for p in pressures}
        spans = {p: (min(c for q, c in peaks if q == p), max(c for q, c in peaks if q == p)) for p in pressures}
        line += ("  Calibration loads' peak change, median (range) per pressure: "
                 + "; ".join(f"{p:g} kPa {medians[p]:.2f} ({spans[p][0]:.2f}-{spans[p][1]:.2f})" for p in pressures)
                 + ".\n")
        heavy = [p for p in pressures if p >= 5]
        if len(heavy) > 1:
            line += (f"  The {heavy[0]:g} to {heavy[-1]:g} kPa loads' median peak changes lie between "
                     f"{min(medians[p] for p in heavy):.2f} and {max(medians[p] for p in heavy):.2f}: "
                     f"{heavy[-1] / heavy[0]:.0f} times the pressure in "
                     f"{max(medians[p] for p in heavy) / min(medians[p] for p in heavy):.2f} times the change.\n")
    top = float(curve.pressure[-1])
    if top >= 20:
        c5, c20 = (float(np.interp(k, curve.pressure, curve.change)) for k in (5.0, 20.0))
        below = float(np.interp(5.0, curve.pressure, curve.change))
        c2 = float(np.interp(2.0, curve.pressure, curve.change))
        line += (f"  5 kPa is read at a change of {c5:.3g}, 20 kPa at {c20:.3g}: four times the pressure in "
                 f"{c20 / c5:.2f} times the change (2 to 5 kPa: {c2:.3g} to {below:.3g}, {below / c2:.2f} times); "
                 f"between them a 1 % error in a 20 kPa pixel's change reads "
                 f"{0.01 * c20 * 15 / max(c20 - c5, 1e-12):.1f} kPa off.\n")
    else:
        slope = (curve.pressure[-1] - curve.pressure[-2]) / max(curve.change[-1] - curve.change[-2], 1e-12)
        line += (f"  The curve's last knot is {top:.1f} kPa: the isotonic fit pools the loads whose peak changes "
                 f"it cannot order into one block read at their mean pressure, so heavier pressures are read only "
                 f"by extrapolating the last segment ({slope:.1f} kPa per unit change).\n")
    return line


# ----------------------------------------------------------------------------------------------------------
# 2. the scene library on the bed


def scene_times(scene, frames: int) -> list[float]:
    """``frames`` times spread over the scene's duration at which someone lies on the bed."""
    candidates = np.linspace(0.02, 0.98, 8 * frames) * scene.duration_s
    on = [float(t) for t in candidates if scene.pressure_at(float(t)).peak_kpa > 1.0]
    if len(on) <= frames:
        return on
    return [on[i] for i in np.linspace(0, len(on) - 1, frames).round().astype(int)]


def bed_frames(bed, protocol, scenes, frames: int):
    """For each scene: the empty mat's frame before it, and its frames with the true field at their times."""
    front = VirtualFrontEnd(bed, protocol, seed=SEED)
    place = placer(bed)
    recorded = {}
    for name in scenes:
        place(None)
        front.time_s = 0.0
        reference = front.acquire().volts
        scene = load_scene(name)
        bed.set_scene(scene)
        shots = []
        for t in scene_times(scene, frames):
            front.time_s = t
            shots.append((t, front.acquire().volts, bed.field_at(t)))
        recorded[name] = (reference, shots)
    place(None)
    return recorded


def read_bed(model, calibration, recorded):
    grid = model.reconstructor.grid
    iterate = calibration.notes["iterate"]
    out = {}
    for name, (reference, shots) in recorded.items():
        rows = []
        for t, volts, field in shots:
            start = time.perf_counter()
            image, info = model.reconstruct(volts, reference, iterate=iterate)
            seconds = time.perf_counter() - start
            kpa = calibration.pressure_kpa(image)
            truth = pixel_average(field, grid)
            true_regions = loaded_regions(truth, grid)
            found_regions = loaded_regions(kpa, grid)
            true_area = loaded_area_cm2(truth, grid, HIGH_PRESSURE_KPA)
            rows.append(dict(t=t, rmse=rmse(kpa, truth, grid), peak=float(np.nanmax(kpa)), true_peak=float(truth.max()),
                             field_peak=field.peak_kpa, area=loaded_area_cm2(kpa, grid, HIGH_PRESSURE_KPA),
                             true_area=true_area, distances=match_regions(true_regions, found_regions),
                             n_true=len(true_regions), n_found=len(found_regions), seconds=seconds,
                             iterations=info["iterations"], kpa=kpa, truth=truth))
        out[name] = rows
    return out


def bed_part(algorithms, frames: int, log):
    layout = get_layout("grid-8x16")
    protocol = default_protocol(layout)
    scenes = builtin_scenes()
    bed = VirtualBed(layout, load_scene(scenes[0]))
    start = time.perf_counter()
    recorded = bed_frames(bed, protocol, scenes, frames)
    log(f"grid-8x16: {sum(len(s) for _, s in recorded.values())} scene frames in {time.perf_counter() - start:.0f} s")
    results, notes = {}, {}
    for algorithm in algorithms:
        start = time.perf_counter()
        model, hit = cached_model(ModelSetup(layout, protocol, ReconstructionOptions(algorithm)), default_cache_dir())
        model_s = time.perf_counter() - start
        peaks = []
        calibration, calibration_s, error = calibrate(model, bed, protocol, layout, peaks=peaks)
        if calibration is None:
            notes[algorithm] = error
            log(f"grid-8x16 {algorithm}: calibration failed: {error}")
            continue
        results[algorithm] = dict(scenes=read_bed(model, calibration, recorded), calibration_s=calibration_s,
                                  model_s=model_s, cached=hit, grid=model.reconstructor.grid,
                                  iterate=calibration.notes["iterate"], curve=calibration.curve,
                                  peaks=peaks)
        log(f"grid-8x16 {algorithm}: model {model_s:.1f} s ({'cached' if hit else 'built'}), calibration "
            f"{calibration_s:.0f} s")
    return results, notes


def bed_table(results):
    headers = ["algorithm", "scene", "frames", "median RMSE kPa", "median true peak kPa (pixel-avg / 10 mm field)",
               "median map peak kPa", "median peak err %", "median true area >= 4.3 kPa cm2",
               "median area err % (>= 4.3 kPa)", "true regions", "found within 100 mm",
               "median centroid dist mm", "iterated frames", "median ms/frame", "calibration s"]
    rows = []
    for algorithm, result in results.items():
        everything = []
        for name, frames in result["scenes"].items():
            everything += frames
            rows.append(bed_row(algorithm, name, frames, result["calibration_s"]))
        rows.append(bed_row(algorithm, "**all**", everything, result["calibration_s"]))
    return table(headers, rows)


def bed_row(algorithm, name, frames, calibration_s):
    distances = np.array([d for f in frames for d in f["distances"]])
    found = np.mean(distances <= FOUND_WITHIN_MM) * 100 if len(distances) else np.nan
    area_error = [100 * (f["area"] / f["true_area"] - 1) for f in frames if f["true_area"] > 0]
    return [algorithm, name, len(frames), fmt(np.median([f["rmse"] for f in frames]), 2),
            f"{np.median([f['true_peak'] for f in frames]):.1f} / {np.median([f['field_peak'] for f in frames]):.1f}",
            fmt(np.median([f["peak"] for f in frames])),
            fmt(100 * np.median([f["peak"] / f["true_peak"] - 1 for f in frames]), 0),
            fmt(np.median([f["true_area"] for f in frames]), 0), fmt(np.median(area_error) if area_error else np.nan, 0),
            len(distances), f"{fmt(found, 0)} %", fmt(np.median(distances) if len(distances) else np.nan, 0),
            f"{sum(f['iterations'] > 0 for f in frames)}/{len(frames)}",
            fmt(1e3 * np.median([f["seconds"] for f in frames]), 0), fmt(calibration_s, 0)]


# ----------------------------------------------------------------------------------------------------------


def figure(examples, bed_results, path):
    plt = pyplot()
    fig, axes = plt.subplots(2, 3, figsize=(13, 7))
    if "greit" in examples:
        grid, rows = examples["greit"]
        for ax, area in zip(axes[0], (4, 9, 25)):
            r = next(r for r in rows if r["area"] == area)
            im = ax.imshow(r["kpa"], origin="lower", extent=(0, grid.width_mm, 0, grid.height_mm), cmap="viridis")
            load = r["load"]
            half = load.side_mm / 2
            ax.add_patch(plt.Rectangle((load.x_mm - half, load.y_mm - half), load.side_mm, load.side_mm, fill=False,
                                       edgecolor="w", linestyle="--"))
            ax.set_title(f"grid-4x4 greit: {area} cm2 at {load.pressure_kpa:.1f} kPa\nmap peak {np.nanmax(r['kpa']):.1f}")
            fig.colorbar(im, ax=ax, label="kPa")
    if "greit" in bed_results:
        result = bed_results["greit"]
        grid = result["grid"]
        frame = result["scenes"]["supine-still"][0] if "supine-still" in result["scenes"] else \
            next(iter(result["scenes"].values()))[0]
        top = max(np.nanmax(frame["kpa"]), frame["truth"].max())
        for ax, data, title in ((axes[1][0], frame["truth"], "true field, pixel-averaged"),
                                (axes[1][1], frame["kpa"], "greit map")):
            im = ax.imshow(data, origin="lower", extent=(0, grid.width_mm, 0, grid.height_mm), vmin=0, vmax=top)
            ax.contour(np.linspace(0, grid.width_mm, grid.cols), np.linspace(0, grid.height_mm, grid.rows),
                       np.nan_to_num(data), levels=[HIGH_PRESSURE_KPA], colors="r", linewidths=0.8)
            ax.set_title(f"bed, supine-still: {title}")
            fig.colorbar(im, ax=ax, label="kPa", shrink=0.7)
        ax = axes[1][2]
        for algorithm, res in bed_results.items():
            d = [x for frames in res["scenes"].values() for f in frames for x in f["distances"]]
            d = np.sort(np.minimum(d, 1000))
            ax.plot(d, np.arange(1, len(d) + 1) / len(d), label=algorithm)
        ax.set_xlabel("centroid distance, true region >= 4.3 kPa to nearest found (mm)")
        ax.set_ylabel("share of true regions")
        ax.legend()
    save_figure(fig, path)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="4 positions per area, greit only on the bed, "
                                                             "2 frames per scene; does not write the report")
    args = parser.parse_args(argv)
    began = time.perf_counter()
    load_start = os.getloadavg()[0]
    positions = 4 if args.quick else POSITIONS
    bed_algorithms = BED_ALGORITHMS[:1] if args.quick else BED_ALGORITHMS
    frames = 2 if args.quick else SCENE_FRAMES

    def log(message):
        print(f"[{time.perf_counter() - began:6.0f} s] {message}", flush=True)

    single, single_notes, examples = single_load_part(positions, ALGORITHMS, log)
    # the 30 % footprint's share of the load's force, for the small-load table
    for algorithm, result in single.items():
        grid = examples[algorithm][0]
        w, h = grid.pixel_mm
        for r in result["rows"]:
            region = peak_region(r["kpa"], grid)
            force = (np.nansum(r["kpa"][region.mask]) * w * h) if region else 0.0
            r["force"] = force / (r["load"].pressure_kpa * r["load"].side_mm ** 2)
    single_table, verdicts = single_load_tables(single)
    small_table = small_load_table(single)
    print(single_table, "\n")
    print(small_table, "\n")
    bed, bed_notes = bed_part(bed_algorithms, frames, log)
    scenes_table = bed_table(bed)
    print(scenes_table, "\n")
    took = time.perf_counter() - began
    log("done")
    if args.quick:
        return
    figure(examples, bed, HERE / "pressure.png")
    text = report(single, single_notes, verdicts, single_table, small_table, bed, bed_notes, scenes_table,
                  took, load_start, os.getloadavg()[0], positions, frames)
    (HERE / "pressure.md").write_text(text)


def report(single, single_notes, verdicts, single_table, small_table, bed, bed_notes, scenes_table, took,
           load_start, load_end, positions, frames) -> str:
    passed = [f"{a} {area} cm2" for (a, area), ok in verdicts.items() if ok]
    failed = [f"{a} {area} cm2" for (a, area), ok in verdicts.items() if not ok]
    notes = "".join(f"* **{a}** could not be calibrated: `{e}`\n" for a, e in {**single_notes}.items())
    bed_failures = "".join(f"* **{a}** on the bed could not be calibrated: `{e}`\n" for a, e in bed_notes.items())

    blur, lumps = blur_notes(single)
    widths = [group_median(res, 4, "width") for res in single.values()]
    widths = [w for w in widths if not lumpy(w, 4) and w > 20]
    width_range = f"{min(widths):.0f} to {max(widths):.0f} mm" if widths else "-"
    bed_loads = calibration_loads(get_layout("grid-8x16"))
    bed_sides = sorted({round(load.side_mm) for load in bed_loads})
    bed_iterates = sorted({res["iterate"] for res in bed.values()})
    not_on_bed = [a for a in ALGORITHMS if a not in BED_ALGORITHMS]
    curves = "".join(curve_note(a, res["curve"], res["peaks"]) for a, res in bed.items())
    speed = ", ".join(f"{a} {1e3 * np.median([r['seconds'] for r in res['rows']]):.0f} ms"
                      for a, res in single.items())
    bed_lines = ""
    for algorithm, result in bed.items():
        frames_all = [f for fr in result["scenes"].values() for f in fr]
        d = np.array([x for f in frames_all for x in f["distances"]])
        bed_lines += (f"* **{algorithm}** on the bed: map RMSE {np.median([f['rmse'] for f in frames_all]):.2f} kPa "
                      f"(median frame); the map's peak is {np.median([f['peak'] for f in frames_all]):.1f} kPa against "
                      f"{np.median([f['true_peak'] for f in frames_all]):.1f} kPa of the pixel-averaged field and "
                      f"{np.median([f['field_peak'] for f in frames_all]):.1f} kPa of the 10 mm field; "
                      f"{np.mean(d <= FOUND_WITHIN_MM) * 100 if len(d) else float('nan'):.0f} % of the "
                      f"{len(d)} true regions >= 4.3 kPa have a found region within {FOUND_WITHIN_MM:.0f} mm "
                      f"(median distance {np.median(d) if len(d) else float('nan'):.0f} mm); "
                      f"{1e3 * np.median([f['seconds'] for f in frames_all]):.0f} ms a frame.\n")
    return f"""# Pressure: end-to-end accuracy of the kPa map, with speed beside it

Command: `{COMMAND}` ({machine()}). The run took {took:.0f} s; the machine's one-minute load
average was {load_start:.1f} at its start and {load_end:.1f} at its end on {os.cpu_count()} cores: the machine is
shared, so timings are noisy and every time here is a median.

The chain is the whole product's: virtual bed (mat mechanics and FEM) -> front end (analogue chain, noise)
-> reconstruction (`ReconstructionModel.reconstruct`, models from `cached_model` in the default cache)
-> pressure calibration (`pressure_calibration` with the default `calibration_loads`, on the same virtual
bed, front end seed 1) -> kPa map (`calibration.pressure_kpa`). The reference is always a frame of the empty mat.

## 1. grid-4x4: single square loads, per algorithm

{positions} loads per area at random places anywhere on the 100 mm mat (centre uniform in
[side/2, 100 - side/2], pressure uniform in [2, 20] kPa, seed {SEED} + area; not the calibration's places),
read as `tests/test_virtual_bed.py` reads them: **peak** = the map's maximum against the load's pressure;
**centre** = `peak_region` (the region down to 30 % of the peak, pressure-weighted); **RMSE** = over the
imaged pixels against `Load.pixel_pressure(grid)`; **area err** = area of the map at >= half the load's
pressure minus the true area; **half-max side** = sqrt of the area of the peak's region at half the map's peak
(the image's width). The same frames are read by every algorithm, each with the `iterate` its calibration
stored: the product's default (`affordable_iterate(16)` = "always") for Gauss-Newton and GREIT;
backprojection cannot iterate and is calibrated and read with `iterate="never"`. Weights are placed by
`placer(bed)` (2 mm cells on this mat). Time per frame is `reconstruct` alone; calibration time includes its 106 bed frames.
Must-hold (9 to 25 cm2): median |peak error| <= 20 % and median centre error <= 3 mm.

{single_table}

{notes}Must-hold rows passing: {", ".join(passed) or "none"}. Failing: {", ".join(failed) or "none"}.

### The 4 cm2 loads: what the blur allows

A 4 cm2 load is 20 mm square. Its image is wider than the load (median half-max side {width_range}
across the algorithms whose image is wider than it), its force (pressure x area) is spread over that width, so
its peak reads low by about the ratio of the areas, (true side / half-max side)^2. The calibration curve is
fitted to the peaks of the 9 to 25 cm2 calibration loads (30 to 50 mm sides) and cannot undo this for a
narrower one. Measured here (medians over {positions} loads):

{blur}
{small_table}

{lumps}
For a 20 mm load what the blur allows is its position (centre error above) and its force, not its peak.

## 2. The scene library on the bed (grid-8x16, 1900 x 900 mm, 128 electrodes)

One calibration per algorithm with the product's defaults (`calibration_loads(grid-8x16)`: {len(bed_loads)} weights of
{bed_sides[0]} to {bed_sides[-1]} mm sides, placed by `placer(bed)` on 10 mm cells; `iterate` left to
`affordable_iterate(128)` = {", ".join(bed_iterates) or "-"}) on one VirtualBed, then for each built-in scenario {frames} frames at times spread over
its duration at which the patient lies on the bed, each read against the empty mat's frame taken before
the scenario. The truth is the scene's field (`bed.field_at(t)`, 10 mm cells) averaged into the image's
pixels (55.9 x 56.3 mm). **peak err** is the map's peak against the pixel-averaged field's peak (the
10 mm field's own peak is shown beside it: no 56 mm pixel can read it); **area err** is the area >= 4.3 kPa
(32 mmHg) against the pixel-averaged field's; each true region >= 4.3 kPa is matched to the nearest
region of the map >= 4.3 kPa (centroid distance; "found" = within {FOUND_WITHIN_MM:.0f} mm).

Deviations from the plan:

* **one-step on the bed**: the map here is the linear reconstruction's, as the product's default gives it.
  `iterate="auto"` or `"always"` on the bed costs minutes per frame (measured on this machine: 4 iterations,
  72 s for a 2 kPa load; 12 iterations, 259 s for a 20 kPa load), hours for a {len(bed_loads)}-load calibration.
* **algorithms**: {", ".join(BED_ALGORITHMS)} on the bed; {", ".join(not_on_bed)} were not run there: each
  needs its own bed model and {len(bed_loads) + 1}-frame calibration, which did not fit the run's ~10 minute budget.

{bed_failures}{scenes_table}

### Where the one-step bed map stops resolving pressure

The calibration curve maps the size of the image's change to kPa. Where the liquid layer under a wide load
bottoms out, the peak changes of the heavier calibration loads bunch together: the curve climbs steeply over a
small range of change (a small error in the change is a large error in kPa) or, where the fit cannot order the
loads at all, pools them into one knot at their mean pressure. The knots of this run, and the calibration
loads' peak changes behind them:

{curves}
`pressure.png`, bottom row: the supine-still frame's pixel-averaged true field beside the greit map (red:
4.3 kPa contour), and the share of true regions found against centroid distance for each bed algorithm.

## What this means

On the thesis's mat the single-load must-hold (9 to 25 cm2, peak within 20 % and centre within 3 mm,
medians) passes for {", ".join(passed) or "nothing"}{"; it fails for " + ", ".join(failed) if failed else ""}.
Reconstruction per frame: {speed} (median, one iterated frame for all but backprojection).
4 cm2 loads read low: their image is wider than the 20 mm load ({width_range} at half maximum) and the
peak falls by about the area ratio (see above).

{bed_lines}
On the bed a 56 mm pixel averages a body's pressure: the pixel-averaged field's peak is far below the
10 mm field's, and the product can only report the former. The bed's numbers are from the one-step map,
calibrated with flat weights much wider than a heel or sacrum; regions of the body smaller than a pixel or two
are where the map misses, as the table's found share and area error show.
"""


if __name__ == "__main__":
    main()
