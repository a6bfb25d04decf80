"""The hand-labelled site maps (tests/data/site_labels) and how a located map is scored against them.

The labels were given by eye on the middle frame of each held-out subject's PmatData posture files (S4, S6,
S11), on the 900 x 1900 mm mat at 10 mm, positions in the body view (along from the head end, across from the
patient's right). A located site agrees with the labels when a labelled spot of the same name lies within
``MATCH_MM`` of it; a labelled spot is found when a located site of its name lies within ``MATCH_MM``.
``MATCH_MM`` is one and a half of the monitor's 30 mm pixels: the located site is a pixel centre, the label a
10 mm cell's.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

LABELS = Path(__file__).resolve().parent.parent / "tests" / "data" / "site_labels"
SUBJECTS = (4, 6, 11)
MATCH_MM = 45.0


@dataclass(frozen=True)
class LabelledSpot:
    subject: int
    posture_file: int
    posture: str
    site: str | None
    along_mm: float
    across_mm: float
    peak_mmhg: float


def labelled_spots(subjects=SUBJECTS, folder: Path = LABELS) -> list[LabelledSpot]:
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


@dataclass(frozen=True)
class Agreement:
    """Located named sites agreeing with a label of the same name, and labelled named spots found."""

    located: int
    located_right: int
    labelled: int
    labelled_found: int
    wrong: tuple[tuple[str, str], ...]      # (located name, what the labels say there) for each disagreement

    @property
    def precision(self) -> float:
        return self.located_right / self.located if self.located else float("nan")

    @property
    def recall(self) -> float:
        return self.labelled_found / self.labelled if self.labelled else float("nan")


def score(located: list[tuple[str, float, float]], labelled: list[LabelledSpot], *,
          loaded_mmhg: float = 32.0) -> Agreement:
    """``located``: (site, along, across) of one map's named sites; ``labelled``: that map's spots. Only
    labelled spots at or above ``loaded_mmhg`` count as spots to be found."""
    named = [s for s in labelled if s.site and s.peak_mmhg >= loaded_mmhg]
    right, wrong = 0, []
    for site, along, across in located:
        near = [s for s in labelled if np.hypot(s.along_mm - along, s.across_mm - across) <= MATCH_MM]
        if any(s.site == site for s in near):
            right += 1
        else:
            said = sorted({str(s.site) for s in near}) or ["no labelled spot"]
            wrong.append((site, "/".join(said)))
    found = sum(any(site == s.site and np.hypot(s.along_mm - along, s.across_mm - across) <= MATCH_MM
                    for site, along, across in located) for s in named)
    return Agreement(len(located), right, len(named), found, tuple(wrong))


def combine(parts: list[Agreement]) -> Agreement:
    return Agreement(sum(p.located for p in parts), sum(p.located_right for p in parts),
                     sum(p.labelled for p in parts), sum(p.labelled_found for p in parts),
                     tuple(w for p in parts for w in p.wrong))
