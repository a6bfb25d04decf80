"""Which site each place of the body is, learned from hand-labelled maps (tests/data/site_labels).

The hand labels name the loaded spots of real in-bed maps (PmatData) by eye, posture by posture; a spot that is
loaded but lies over no bony prominence (a buttock, the thoracic spine, a thigh) is labelled None. Each labelled
spot becomes a point (s, u) in the body frame fitted to its map
(:func:`~appliance.alerts.body_frame.body_coordinates`), kept per posture. A place of a new map takes the
vote of its ``NEIGHBOURS`` nearest points of its posture, each weighted by
1 / (distance + ``VOTE_SOFTENING``), ``u`` distances counted ``ACROSS_WEIGHT`` times (sides and the midline
matter more than a few cm along); it stays unnamed beyond ``REACH`` of every point (no label ever lay there).

Left and right: every spot also teaches its mirror image (u turned over, the sites' sides swapped, the posture's
side swapped), so a right-side posture learns from the left-side maps too and supine maps are symmetric.

These constants were chosen by leave-one-subject-out cross-validation over the eight training subjects, the
locator's label of a loaded labelled spot being its pixel's (benchmarks/site_labels.py): 0.78 of all loaded
spots and 0.77 of the hand-named ones right (the hand-set landmarks before it: 0.67 and 0.52); k from 5 to 17
and the across weight from 1 to 3 all gave 0.77-0.78, a relative-pressure feature and pooling 60 with 90
degrees did not help. tests/test_sites.py recomputes it. Only the training subjects
(``site_table_fit.TRAINING_SUBJECTS``) are fitted: S4, S6 and S11 are held out for validating the product
and must never be read here. Prone, sitting on the edge and out of bed have no labels: :mod:`appliance.alerts.sites`
keeps rules for them.

The table is fitted from the labels by :mod:`appliance.alerts.site_table_fit`, which rebuilds the shipped
``site_table.json``.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from appliance.alerts.anatomy import SITES, check_posture
from appliance.errors import DataFileInvalid

TABLE_PATH = Path(__file__).with_name("site_table.json")
LABELLED_POSTURES = ("supine", "inclined", "left-30", "right-30", "left-60", "right-60", "left-90", "right-90",
                     "fetal-left", "fetal-right")
NEIGHBOURS, ACROSS_WEIGHT, VOTE_SOFTENING, REACH = 7, 2.0, 0.01, 0.12
DECIMALS = 4


@dataclass(frozen=True)
class LabelledPoint:
    """One hand-labelled spot in its map's body frame."""

    subject: int
    posture: str
    s: float
    u: float
    site: str | None


@dataclass(frozen=True)
class SiteTable:
    """Per posture, the labelled points: ``(n, 2)`` array of (s, u) and their sites (None: no bony prominence)."""

    points: dict[str, tuple[np.ndarray, tuple[str | None, ...]]]

    def sites_at(self, posture: str, s: np.ndarray, u: np.ndarray) -> list[str | None]:
        """The site voted for at each body place (s, u) lying in ``posture`` (see the module's notes)."""
        s, u = np.atleast_1d(np.asarray(s, float)), np.atleast_1d(np.asarray(u, float))
        su, sites = self.points[posture]
        if len(s) == 0 or len(sites) == 0:
            return [None] * len(s)
        names = sorted(set(sites), key=lambda n: "" if n is None else n)
        codes = np.array([names.index(n) for n in sites])
        distance = np.hypot(su[None, :, 0] - s[:, None], (su[None, :, 1] - u[:, None]) * ACROSS_WEIGHT)
        k = min(NEIGHBOURS, len(sites))
        nearest = np.argpartition(distance, k - 1, axis=1)[:, :k]
        near = np.take_along_axis(distance, nearest, axis=1)
        votes = np.zeros((len(s), len(names)))
        np.add.at(votes, (np.arange(len(s))[:, None], codes[nearest]), 1.0 / (near + VOTE_SOFTENING))
        winner = votes.argmax(axis=1)
        return [None if near[i].min() > REACH else names[winner[i]] for i in range(len(s))]

    @classmethod
    def from_points(cls, points: list[LabelledPoint]) -> SiteTable:
        """The table of ``points`` and their mirror images, rounded as stored."""
        table: dict[str, list[tuple[float, float, str | None]]] = {p: [] for p in LABELLED_POSTURES}
        for p in points:
            table[p.posture].append((round(p.s, DECIMALS), round(p.u, DECIMALS), p.site))
            table[mirrored_posture(p.posture)].append((round(p.s, DECIMALS), round(-p.u, DECIMALS),
                                                       mirrored_site(p.site)))
        return cls({posture: (np.array([(s, u) for s, u, _ in rows], dtype=float).reshape(-1, 2),
                              tuple(site for _, _, site in rows)) for posture, rows in table.items()})

    def to_json(self) -> dict:
        return {posture: [[float(s), float(u), site] for (s, u), site in zip(su, sites)]
                for posture, (su, sites) in self.points.items()}

    @classmethod
    def from_json(cls, data: dict) -> SiteTable:
        try:
            return cls({check_posture(posture): (np.array([row[:2] for row in rows], dtype=float).reshape(-1, 2),
                                                 tuple(row[2] if row[2] is None else _known(row[2]) for row in rows))
                        for posture, rows in data["postures"].items()})
        except (KeyError, TypeError, IndexError, ValueError) as exc:
            raise DataFileInvalid(f"site table: {exc}") from None


def _known(site: str) -> str:
    if site not in SITES:
        raise ValueError(f"unknown site {site!r}")
    return site


@functools.cache
def load_table(path: Path = TABLE_PATH) -> SiteTable:
    """The shipped table (read once)."""
    try:
        return SiteTable.from_json(json.loads(Path(path).read_text(encoding="utf-8")))
    except (OSError, json.JSONDecodeError) as exc:
        raise DataFileInvalid(f"site table {path} cannot be read: {exc}") from None


def mirrored_site(site: str | None) -> str | None:
    """The same site on the other side: ``heel-left`` is ``heel-right``; the sacrum is itself."""
    if site is None:
        return None
    name, _, side = site.rpartition("-")
    return f"{name}-{'right' if side == 'left' else 'left'}" if side in ("left", "right") else site


def mirrored_posture(posture: str) -> str:
    """The posture seen in a mirror: lying on the other side (supine is itself)."""
    return posture.replace("left", "@").replace("right", "left").replace("@", "right")
