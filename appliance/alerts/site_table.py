"""Which site each place of the body is, learned from hand-labelled maps (tests/data/site_labels).

The hand labels name the loaded spots of real in-bed maps (PmatData) by eye, posture by posture; a spot that is
loaded but lies over no bony prominence (a buttock, the thoracic spine, a thigh) is labelled None. Each labelled
spot becomes a point of the monitor pixel it lies in: where that pixel lies in the body frame fitted to its map,
(s, u) (:func:`~appliance.alerts.body_frame.body_coordinates`), and how heavily it is loaded against the body's
own load (:func:`relative_load`), kept per posture. A place of a new map takes the vote of its ``NEIGHBOURS``
nearest points of its posture, each weighted by 1 / (distance + ``VOTE_SOFTENING``), ``u`` distances counted
``ACROSS_WEIGHT`` times (sides and the midline matter more than a few cm along) and relative loads
``LOAD_WEIGHT`` times per unit of their logarithm (the labels name a hip's or a pelvis's hot spot, and leave the
fainter spots around it unnamed); it stays unnamed beyond ``REACH`` (in s and weighted u) of every point (no label
ever lay there).

Left and right: every spot also teaches its mirror image (u turned over, the sites' sides swapped, the posture's
side swapped), so a right-side posture learns from the left-side maps too and supine maps are symmetric.

These constants were chosen by leave-one-subject-out cross-validation over the eight training subjects, the
locator's label of a loaded labelled spot being its pixel's, on the true maps and on the maps read through the
whole chain (``python benchmarks/site_labels.py --loso [--chain MODEL_CACHE]``). With the labels as given under
one convention (tests/data/site_labels/CONVENTION.md) and the trochanter's reach of :mod:`appliance.alerts.sites`,
k of 7 and 11, across weights of 2 and 3 and load weights of 0, 0.03 and 0.06 gave 0.77-0.80 of the loaded spots
right, these the best (0.800); measuring u from the pelvis's midline lying on the back
(:mod:`appliance.alerts.body_frame`) was chosen on the earlier labels (0.81 against 0.80 for the local midline).
tests/test_sites.py recomputes it. Only the training subjects (``site_table_fit.TRAINING_SUBJECTS``) are fitted:
S4, S6 and S11 are held out for validating the product and must never be read here. Prone, sitting on the edge
and out of bed have no labels: :mod:`appliance.alerts.sites` keeps rules for them.

The table is fitted from the labels by :mod:`appliance.alerts.site_table_fit`, which rebuilds the shipped
``site_table.json``.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from appliance.alerts.anatomy import SITES, BodyView, check_posture
from appliance.alerts.body_frame import CONTACT_KPA, body_contact
from appliance.errors import DataFileInvalid

TABLE_PATH = Path(__file__).with_name("site_table.json")
LABELLED_POSTURES = ("supine", "inclined", "left-30", "right-30", "left-60", "right-60", "left-90", "right-90",
                     "fetal-left", "fetal-right")
NEIGHBOURS, ACROSS_WEIGHT, LOAD_WEIGHT, VOTE_SOFTENING, REACH = 7, 2.0, 0.03, 0.01, 0.12
LOAD_REFERENCE = 95.0
"""The body's own load: this percentile of the loads of the cells it touches (a heavy patient, or a mat reading
high, loads every place more, and the hot spots stay the hot spots)."""
DECIMALS = 4


@dataclass(frozen=True)
class LabelledPoint:
    """One hand-labelled spot: its pixel in its map's body frame, and that pixel's relative load."""

    subject: int
    posture: str
    s: float
    u: float
    load: float
    site: str | None


@dataclass(frozen=True)
class SiteTable:
    """Per posture, the labelled points: ``(n, 3)`` array of (s, u, relative load) and their sites (None: no bony
    prominence)."""

    points: dict[str, tuple[np.ndarray, tuple[str | None, ...]]]

    def sites_at(self, posture: str, s: np.ndarray, u: np.ndarray, load: np.ndarray) -> list[str | None]:
        """The site voted for at each body place (s, u) of relative load ``load`` lying in ``posture`` (see the
        module's notes)."""
        s, u, load = (np.atleast_1d(np.asarray(v, float)) for v in (s, u, load))
        sul, sites = self.points[posture]
        if len(s) == 0 or len(sites) == 0:
            return [None] * len(s)
        names = sorted(set(sites), key=lambda n: "" if n is None else n)
        codes = np.array([names.index(n) for n in sites])
        where = np.hypot(sul[None, :, 0] - s[:, None], (sul[None, :, 1] - u[:, None]) * ACROSS_WEIGHT)
        distance = np.hypot(where, (sul[None, :, 2] - load[:, None]) * LOAD_WEIGHT)
        k = min(NEIGHBOURS, len(sites))
        nearest = np.argpartition(distance, k - 1, axis=1)[:, :k]
        near = np.take_along_axis(distance, nearest, axis=1)
        votes = np.zeros((len(s), len(names)))
        np.add.at(votes, (np.arange(len(s))[:, None], codes[nearest]), 1.0 / (near + VOTE_SOFTENING))
        winner = votes.argmax(axis=1)
        unseen = where.min(axis=1) > REACH
        return [None if unseen[i] else names[winner[i]] for i in range(len(s))]

    @classmethod
    def from_points(cls, points: list[LabelledPoint]) -> SiteTable:
        """The table of ``points`` and their mirror images, rounded as stored."""
        table: dict[str, list[tuple[float, float, float, str | None]]] = {p: [] for p in LABELLED_POSTURES}
        for p in points:
            s, u, load = (round(v, DECIMALS) for v in (p.s, p.u, p.load))
            table[p.posture].append((s, u, load, p.site))
            table[mirrored_posture(p.posture)].append((s, -u, load, mirrored_site(p.site)))
        return cls({posture: (np.array([row[:3] for row in rows], dtype=float).reshape(-1, 3),
                              tuple(row[3] for row in rows)) for posture, rows in table.items()})

    def to_json(self) -> dict:
        return {posture: [[*(float(v) for v in sul), site] for sul, site in zip(points, sites)]
                for posture, (points, sites) in self.points.items()}

    @classmethod
    def from_json(cls, data: dict) -> SiteTable:
        try:
            return cls({check_posture(posture): (np.array([row[:3] for row in rows], dtype=float).reshape(-1, 3),
                                                 tuple(row[3] if row[3] is None else _known(row[3]) for row in rows))
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


def relative_load(view: BodyView, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """The natural logarithm of the load of each cell (rows, cols) of ``view`` over the body's own load
    (``LOAD_REFERENCE``); a cell below contact counts as at contact."""
    kpa = np.asarray(view.kpa, dtype=float)
    touched = kpa[body_contact(kpa)]
    reference = max(float(np.percentile(touched, LOAD_REFERENCE)) if touched.size else 0.0, CONTACT_KPA)
    return np.log(np.maximum(kpa[rows, cols], CONTACT_KPA) / reference)


def mirrored_site(site: str | None) -> str | None:
    """The same site on the other side: ``heel-left`` is ``heel-right``; the sacrum is itself."""
    if site is None:
        return None
    name, _, side = site.rpartition("-")
    return f"{name}-{'right' if side == 'left' else 'left'}" if side in ("left", "right") else site


def mirrored_posture(posture: str) -> str:
    """The posture seen in a mirror: lying on the other side (supine is itself)."""
    return posture.replace("left", "@").replace("right", "left").replace("@", "right")
