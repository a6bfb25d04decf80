"""Which curve reads people's peaks: regressing pressure on the change, or matching the two distributions?
And does the head end of the bed need its own?

    python benchmarks/calibration_curve.py      # writes benchmarks/calibration_curve.md (about 5 min)

The bed is calibrated from people's maps (``appliance calibrate pressure --maps``): every pixel of every map of
the training subjects gives a reconstructed change and a true pressure, and one monotone curve turns one into
the other. Two ways to fit it:

* **regression**: isotonic regression of pressure on change (:func:`appliance.core.pressure.fit_pressure_curve`),
  the mean pressure of the pixels showing each change;
* **matched**: the k-th largest change reads the k-th largest pressure
  (:func:`appliance.core.pressure.matched_curve`);
* **matched, head end its own**: as matched, with a second matched curve for the first ``HEAD_END_MM`` of the
  bed, where the head lies (:func:`appliance.calibration.map_curves`, as the shipped calibration is made).

The choice is made on the training subjects alone (S1-S3, S5, S7-S10), leave one subject out: each subject's
maps read by the curve fitted on the seven others. The held-out subjects (S4, S6, S11), read by the curve
fitted on all eight, are reported after the choice and were not used for it. Maps are the middle frame of each
of the 17 posture files through the chosen bed design of ``benchmarks/bed.py`` (grid-16x32), imaged as the
calibration images them; spots, sites and peak errors as that benchmark judges them.
"""

from __future__ import annotations

import appliance  # noqa: F401  (first: it pins BLAS to one thread before numpy loads)

import contextlib
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).parent))
import bed
from report import machine, table

from appliance.calibration import HEAD_END_MM, affordable_iterate, map_curves
from appliance.core.model_cache import cached_model
from appliance.core.pressure import KPA_PER_MMHG, fit_pressure_curve, matched_curve
from appliance.sim.recordings import pmat_map_loads

FITS = {"regression": (fit_pressure_curve, False), "matched": (matched_curve, False),
        "matched, head end its own": (matched_curve, True)}
HEAD_ENDS_MM = (180.0, 210.0, 240.0, 270.0, 300.0, 360.0)
QUIET_MMHG = 20.0
"""A pixel read at 32 mmHg or more with no true pressure of 20 mmHg within one pixel counts as load read where
there is none."""


def images(cache: Path) -> tuple[dict, object, object]:
    """{(subject, posture): (image, truth kPa)} for every map of every subject, on the chosen design's pixels;
    the design's layout and pixel grid."""
    design = next(d for d in bed.DESIGNS if d.name == bed.CHOSEN)
    model, _ = cached_model(design.setup(), cache)
    recorded = bed.RecordedMat(design.mat)
    iterate = affordable_iterate(model.setup.layout.n_electrodes)
    recorded.place(None)
    reference = recorded.acquire().volts
    out = {}
    for subject in bed.TRAINING + bed.HELD_OUT:
        for load in pmat_map_loads(bed.PMAT, [subject]):
            recorded.place(load)
            image, _ = model.reconstruct(recorded.acquire().volts, reference, iterate=iterate)
            out[(subject, int(load.name.split("/")[1].split("#")[0]))] = (image, load.pixel_pressure(
                model.reconstructor.grid))
        print(f"S{subject} imaged", flush=True)
    return out, model.setup.layout, model.reconstructor.grid


def fitted(how: str, maps: dict, subjects, layout, grid):
    """(curve, zone curves) of ``how`` fitted to the maps of ``subjects``."""
    fit, head_end = FITS[how]
    pairs = [maps[k] for k in maps if k[0] in subjects]
    return map_curves([image for image, _ in pairs], [truth for _, truth in pairs], layout, grid, fit=fit,
                      head_end=head_end)


@contextlib.contextmanager
def patched_head_end(length_mm: float):
    """The calibration's head end set to ``length_mm`` for a while."""
    import appliance.calibration as calibration

    kept, calibration.HEAD_END_MM = calibration.HEAD_END_MM, length_mm
    try:
        yield
    finally:
        calibration.HEAD_END_MM = kept


def read_kpa(curves, image: np.ndarray) -> np.ndarray:
    curve, zones = curves
    pressure = curve.pressure_kpa(image)
    for zone in zones:
        pressure = np.where(zone.mask, zone.curve.pressure_kpa(image), pressure)
    return pressure


def judged(curves, maps: dict, subjects) -> tuple[list, int, int]:
    """(spots, pixels read loaded where nothing is, maps) of ``subjects`` read by ``curves``."""
    spots, quiet_read, count = [], 0, 0
    for (subject, posture), (image, truth_kpa) in maps.items():
        if subject not in subjects:
            continue
        read = read_kpa(curves, image) / KPA_PER_MMHG
        truth = truth_kpa / KPA_PER_MMHG
        spots += bed.spots_of(truth, read, subject, posture)
        near = ndimage.binary_dilation(np.nan_to_num(truth) >= QUIET_MMHG, structure=np.ones((3, 3)))
        quiet_read += int(((np.nan_to_num(read) >= bed.THRESHOLD_MMHG) & ~near).sum())
        count += 1
    return spots, quiet_read, count


def row(label: str, how: str, spots: list, quiet_read: int, count: int) -> list:
    errors = np.array([s.error for s in spots])
    return [label, how, len(spots), f"{np.mean([s.seen for s in spots]):.1%}", f"{np.median(np.abs(errors)):.1%}",
            f"{np.median(errors):+.1%}", f"{quiet_read / count:.2f}"]


def site_row(how: str, spots: list) -> list:
    return [how] + [f"{np.median([s.error for s in spots if s.site == site]):+.1%}"
                    if any(s.site == site for s in spots) else "-" for site in bed.SITES]


def main() -> None:
    import tempfile

    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as cache:
        maps, layout, grid = images(Path(cache))
    rows, held_sites = [], []
    for how in FITS:
        loso = [judged(fitted(how, maps, [s for s in bed.TRAINING if s != left], layout, grid), maps, [left])
                for left in bed.TRAINING]
        rows.append(row("training, leave one subject out", how, [s for spots, _, _ in loso for s in spots],
                        sum(q for _, q, _ in loso), sum(n for *_, n in loso)))
    ends = []
    for length in HEAD_ENDS_MM:
        with patched_head_end(length):
            spots = [s for left in bed.TRAINING for s in judged(fitted(
                "matched, head end its own", maps, [s for s in bed.TRAINING if s != left], layout, grid), maps,
                [left])[0]]
        errors = np.array([s.error for s in spots])
        ends.append([f"{length:g}", f"{np.median(np.abs(errors)):.1%}", f"{np.median(errors):+.1%}",
                     f"{np.median([s.error for s in spots if s.site == 'head']):+.1%}"])
    for how in FITS:
        spots, quiet, count = judged(fitted(how, maps, bed.TRAINING, layout, grid), maps, bed.HELD_OUT)
        rows.append(row("held-out S4, S6, S11", how, spots, quiet, count))
        held_sites.append(site_row(how, spots))
    report = f"""# Pressure curve from people's maps: regression or matched distributions, one curve or the head end's own

Made by `python benchmarks/calibration_curve.py` on {machine()}; {time.perf_counter() - start:.0f} s.

The middle frame of each of the 17 posture files of every PmatData subject through the bed's chosen design
(grid-16x32, as `benchmarks/bed.py` builds it), imaged as the calibration images it; a spot is a true region at
or above 32 mmHg peaking at 40 mmHg or more, its peak error the highest pressure read within one pixel against
the true peak (as `benchmarks/bed.py`). "Quiet pixels read loaded": pixels read at 32 mmHg or more with no true
pressure of {QUIET_MMHG:.0f} mmHg within one pixel, per map. The curves were chosen on the first three rows (training
subjects, each read by the curves of the seven others); the held-out rows came after the choice. The head
end's curve covers the first {HEAD_END_MM:g} mm of the bed, the middle of the lengths that did best in the same
study:

{table(["head end (mm)", "median |peak error|", "median peak error", "heads' median peak error"], ends)}

{table(["maps", "curve", "spots", "seen", "median |peak error|", "median peak error",
        "quiet pixels read loaded per map"], rows)}

Median peak error per body site, held-out subjects:

{table(["curve"] + list(bed.SITES), held_sites)}

The regression gives each change the mean pressure of the pixels that show it; the change is noisy, so the
pixels showing the largest changes include many that are less loaded, and the highest pressures are read low.
Matching the distributions reads the largest changes as the largest pressures. The image is least sensitive at
the mat's end, where the head lies, so one curve for the whole bed reads heads low; a curve of its own for the
head end reads them at their height. The shipped calibration (`appliance/sim/calibrations/grid-16x32.json`) is
made the third way.
"""
    (Path(__file__).parent / "calibration_curve.md").write_text(report, encoding="utf-8")
    print(report)


if __name__ == "__main__":
    main()
