"""Which curve reads people's peaks: regressing pressure on the change, or matching the two distributions?

    python benchmarks/calibration_curve.py      # writes benchmarks/calibration_curve.md (about 5 min)

The bed is calibrated from people's maps (``appliance calibrate pressure --maps``): every pixel of every map of
the training subjects gives a reconstructed change and a true pressure, and one monotone curve turns one into
the other. Two ways to fit it:

* **regression**: isotonic regression of pressure on change (:func:`appliance.core.pressure.fit_pressure_curve`),
  the mean pressure of the pixels showing each change;
* **matched**: the k-th largest change reads the k-th largest pressure
  (:func:`appliance.core.pressure.matched_curve`).

The choice is made on the training subjects alone (S1-S3, S5, S7-S10), leave one subject out: each subject's
maps read by the curve fitted on the seven others. The held-out subjects (S4, S6, S11), read by the curve
fitted on all eight, are reported after the choice and were not used for it. Maps are the middle frame of each
of the 17 posture files through the chosen bed design of ``benchmarks/bed.py`` (grid-16x32), imaged as the
calibration images them; spots, sites and peak errors as that benchmark judges them.
"""

from __future__ import annotations

import appliance  # noqa: F401  (first: it pins BLAS to one thread before numpy loads)

import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).parent))
import bed
from report import machine, table

from appliance.calibration import affordable_iterate
from appliance.core.model_cache import cached_model
from appliance.core.pressure import KPA_PER_MMHG, fit_pressure_curve, matched_curve
from appliance.sim.recordings import pmat_map_loads

FITS = {"regression": fit_pressure_curve, "matched": matched_curve}
QUIET_MMHG = 20.0
"""A pixel read at 32 mmHg or more with no true pressure of 20 mmHg within one pixel counts as load read where
there is none."""


def images(cache: Path) -> dict:
    """{(subject, posture): (image, truth kPa)} for every map of every subject, on the chosen design's pixels."""
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
    return out


def fitted(how: str, maps: dict, subjects) -> object:
    inside = np.isfinite(next(iter(maps.values()))[0])
    pairs = [maps[k] for k in maps if k[0] in subjects]
    sizes = np.clip(-np.array([image[inside] for image, _ in pairs]), 0.0, None)
    return FITS[how](sizes, np.array([truth[inside] for _, truth in pairs]))


def judged(curve, maps: dict, subjects) -> tuple[list, int, int]:
    """(spots, pixels read loaded where nothing is, maps) of ``subjects`` read by ``curve``."""
    spots, quiet_read, count = [], 0, 0
    for (subject, posture), (image, truth_kpa) in maps.items():
        if subject not in subjects:
            continue
        read = curve.pressure_kpa(image) / KPA_PER_MMHG
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
        maps = images(Path(cache))
    rows, held_sites = [], []
    for how in FITS:
        loso = [judged(fitted(how, maps, [s for s in bed.TRAINING if s != left]), maps, [left])
                for left in bed.TRAINING]
        rows.append(row("training, leave one subject out", how, [s for spots, _, _ in loso for s in spots],
                        sum(q for _, q, _ in loso), sum(n for *_, n in loso)))
    for how in FITS:
        spots, quiet, count = judged(fitted(how, maps, bed.TRAINING), maps, bed.HELD_OUT)
        rows.append(row("held-out S4, S6, S11", how, spots, quiet, count))
        held_sites.append(site_row(how, spots))
    report = f"""# Pressure curve from people's maps: regression or matched distributions

Made by `python benchmarks/calibration_curve.py` on {machine()}; {time.perf_counter() - start:.0f} s.

The middle frame of each of the 17 posture files of every PmatData subject through the bed's chosen design
(grid-16x32, as `benchmarks/bed.py` builds it), imaged as the calibration images it; a spot is a true region at
or above 32 mmHg peaking at 40 mmHg or more, its peak error the highest pressure read within one pixel against
the true peak (as `benchmarks/bed.py`). "Quiet pixels read loaded": pixels read at 32 mmHg or more with no true
pressure of {QUIET_MMHG:.0f} mmHg within one pixel, per map. The curve was chosen on the first two rows (training
subjects, each read by the curve of the seven others); the held-out rows came after the choice.

{table(["maps", "curve", "spots", "seen", "median |peak error|", "median peak error",
        "quiet pixels read loaded per map"], rows)}

Median peak error per body site, held-out subjects:

{table(["curve"] + list(bed.SITES), held_sites)}

The regression gives each change the mean pressure of the pixels that show it; the change is noisy, so the
pixels showing the largest changes include many that are less loaded, and the highest pressures are read low.
Matching the distributions reads the largest changes as the largest pressures; the shipped calibration
(`appliance/sim/calibrations/grid-16x32.json`) is made that way.
"""
    (Path(__file__).parent / "calibration_curve.md").write_text(report, encoding="utf-8")
    print(report)


if __name__ == "__main__":
    main()
