"""The hand-labelled site maps (tests/data/site_labels) and how located sites are scored against them.

The labels were given by eye on the middle frame of each PmatData posture file (900 x 1900 mm mat, 10 mm
cells), positions in the body view (along from the head end, across from the patient's right); a spot is
named a site or left unnamed (``None``: a buttock, thigh, calf, hand). Subjects S4, S6 and S11 are the
held-out ones; the others' labels are for fitting.

A labelled spot counts when it is loaded on the monitor's pixels: the map there, within one pixel of it, is at
or above 32 mmHg. The locator's label for it is the site the locator gives the cell (monitor pixel) the spot
lies in (:func:`appliance.alerts.sites.label_cells`; unnamed for a cell below the locator's floor): the label the
monitor gives the tissue there, found without looking at the hand's label. It is right when it equals the hand's
label, unnamed for unnamed included. (Before the locator labelled every cell, the label was the site of the
located spot nearest within 45 mm; a site's second spot, such as a sacrum labelled twice, then counted as
unnamed however the locator read it.)
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

LABELS = Path(__file__).resolve().parent.parent / "tests" / "data" / "site_labels"
HELD_OUT = (4, 6, 11)
MATCH_MM = 45.0
"""How near a true map's peak must lie to a labelled site to be its peak: one and a half 30 mm pixels."""
LOADED_KPA = 32 * 0.133322


@dataclass(frozen=True)
class LabelledSpot:
    subject: int
    posture_file: int
    posture: str
    site: str | None
    along_mm: float
    across_mm: float
    peak_mmhg: float


def labelled_spots(subjects=HELD_OUT, folder: Path = LABELS) -> list[LabelledSpot]:
    """Every labelled spot of ``subjects``, named or not."""
    spots = []
    for subject in subjects:
        data = json.loads((folder / f"pmatdata-S{subject}.json").read_text(encoding="utf-8"))
        for entry in data["maps"]:
            spots += [LabelledSpot(subject, entry["posture_file"], entry["posture"], s["site"], s["along_mm"],
                                   s["across_mm"], s["peak_mmhg"]) for s in entry["spots"]]
    return spots


def site_positions(spots: list[LabelledSpot], subject: int, posture_file: int) -> dict[str, tuple[float, float]]:
    """Named sites of one labelled map: (along, across) mm; a site labelled twice keeps its higher spot."""
    out: dict[str, tuple[float, float, float]] = {}
    for s in spots:
        if s.subject == subject and s.posture_file == posture_file and s.site:
            if s.site not in out or s.peak_mmhg > out[s.site][2]:
                out[s.site] = (s.along_mm, s.across_mm, s.peak_mmhg)
    return {site: (a, c) for site, (a, c, _) in out.items()}


def labels_at_spots(true_view, cell_labels: np.ndarray, spots: list[LabelledSpot]) -> list[tuple[str | None, str | None, str]]:
    """(hand label, locator's label, posture) of each labelled spot of one map that is loaded on ``true_view``
    (a :class:`~appliance.alerts.anatomy.BodyView` of the true map on the monitor's pixels); ``cell_labels``:
    the locator's site for each pixel (:func:`~appliance.alerts.sites.label_cells`, on the true map or on a
    map read through the chain)."""
    out = []
    for spot in spots:
        row, col = int(spot.along_mm // true_view.pitch_mm[0]), int(spot.across_mm // true_view.pitch_mm[1])
        if true_view.kpa[max(row - 1, 0):row + 2, max(col - 1, 0):col + 2].max() < LOADED_KPA:
            continue
        out.append((spot.site, cell_labels[row, col], spot.posture))
    return out
