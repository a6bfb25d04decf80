"""The words the alert layer reasons in: postures, tissue sites, and the map seen as a body.

A pressure map comes in the mat's own coordinates (the pixel grid's x and y, mm).
Posture and sites are about the body lying on it, so both work on a
:class:`BodyView`: the map turned so that rows run from the head end of the mat to
the foot end and columns run from the patient's right to the patient's left: seen
from above with the head at the top, a supine patient's left hand lies on the
viewer's right. It is the frame the virtual body
uses (:mod:`appliance.sim.body`: u towards the patient's left at +x, head at
y = 0). Every result found in the view is carried back to mat millimetres with
:meth:`BodyView.mat_mm`, so events say where on the mat a site is.

The patient is assumed to lie head towards the head end of the mat: that end is
fixed by the bed (the mat is fitted with its head end at the bed's head board).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TypeGuard

import numpy as np

from appliance.calibration import BED_MIN_LENGTH_MM
from appliance.core.pixels import PixelGrid
from appliance.errors import ConfigError

LYING = ("supine", "prone", "left-30", "left-60", "left-90", "right-30", "right-60", "right-90",
         "fetal-left", "fetal-right")
"""Postures in which a patient lies: a change from one to another is a repositioning."""

POSTURES = LYING + ("inclined", "sitting-edge", "out-of-bed")
"""Every posture the monitor names. ``left-30`` is rolled 30 degrees onto the patient's left side (the
left side down, as on a wedge), ``left-90`` lies fully on it; ``inclined`` is supine with the head of
the bed raised; ``sitting-edge`` sits on a long edge of the mat, feet on the floor."""

POSTURE_WORDS = {"supine": "on the back", "prone": "on the front", "left-30": "left side, 30 degrees",
                 "left-60": "left side, 60 degrees", "left-90": "on the left side",
                 "right-30": "right side, 30 degrees", "right-60": "right side, 60 degrees",
                 "right-90": "on the right side", "fetal-left": "curled on the left side",
                 "fetal-right": "curled on the right side", "inclined": "head of bed raised",
                 "sitting-edge": "sitting on the edge", "out-of-bed": "out of bed"}


def posture_side(posture: str) -> str | None:
    """``"left"`` or ``"right"`` for a posture lying on that side, None for the others."""
    check_posture(posture)
    for side in ("left", "right"):
        if posture.startswith(f"{side}-") or posture == f"fetal-{side}":
            return side
    return None


def posture_group(posture: str) -> str:
    """The four groups a posture falls in for repositioning: supine (with the head raised), left, right,
    and prone or other (prone, sitting on the edge, out of bed)."""
    side = posture_side(posture)
    if side:
        return side
    return "supine" if posture in ("supine", "inclined") else "prone/other"


def in_bed(posture: str | None) -> TypeGuard[str]:
    """Lying, or sitting up in bed with the head of the bed raised (which counts as lying on the back)."""
    return posture in LYING or posture == "inclined"


def tilt_deg(posture: str) -> int | None:
    """How far a side posture rolls onto its side: 30, 60 or 90 (curled up counts as 90); None otherwise."""
    if posture_side(posture) is None:
        return None
    return 90 if posture.startswith("fetal") else int(posture.rsplit("-", 1)[1])


def check_posture(posture) -> str:
    """``posture`` if the monitor knows it; otherwise a ConfigError naming it and the known ones."""
    if posture not in POSTURES:
        raise ConfigError(f"unknown posture {posture!r}: use one of {', '.join(POSTURES)}")
    return posture


_PAIRED = ("scapula", "elbow", "ischium", "trochanter", "shoulder", "ear", "knee", "heel", "malleolus",
           "iliac-crest", "toes")
SITES = tuple(sorted(("occiput", "sacrum", "face", "chest")
                     + tuple(f"{name}-{side}" for name in _PAIRED for side in ("left", "right"))))
"""Every tissue site the monitor names: the bony prominences where pressure injuries form (NPIAP), each
paired one with the patient's side. ``sacrum`` covers the sacrum and coccyx, ``heel`` the posterior heel
(supine), ``malleolus`` the ankle bones a side-lying patient rests on, ``ear`` the side of the head, and
``face``, ``chest``, ``iliac-crest``, ``knee`` and ``toes`` the prone patient's front."""


SMALL_MAT_SITE = "mat"
"""The one site of a small mat (a test sensor): no body lies on it, so all of it is one site."""

UNIDENTIFIED_SITE = "unidentified"
"""Load on a bed that is no body: far less than a person's weight (heels alone on the mat, a patient getting
out), so no site can be named from anatomy. Its tissue is still dosed, as one site, so that it can never go
unwatched; its alarms name where the load lies."""


def check_site(site) -> str:
    """``site`` if the monitor knows it; otherwise a ConfigError naming it and the known ones."""
    if site not in SITES:
        raise ConfigError(f"unknown site {site!r}: use one of {', '.join(SITES)}")
    return site


def site_words(site: str) -> str:
    """A site in plain words: ``heel-left`` is "left heel", ``iliac-crest-right`` "right iliac crest"."""
    if site == SMALL_MAT_SITE:
        return "sensor"
    if site == UNIDENTIFIED_SITE:
        return "unidentified loaded spot"
    check_site(site)
    name, _, side = site.rpartition("-")
    if side in ("left", "right"):
        return f"{side} {name.replace('-', ' ')}"
    return site.replace("-", " ")


@dataclass(frozen=True)
class BodyView:
    """A map seen as the body: ``kpa`` rows head end to foot end, columns patient's right to left, cells of
    ``pitch_mm`` (along, across); ``transposed`` says whether the mat's x runs along the body."""

    kpa: np.ndarray
    pitch_mm: tuple[float, float]
    transposed: bool

    @property
    def shape(self) -> tuple[int, int]:
        return self.kpa.shape

    @property
    def length_mm(self) -> float:
        return self.kpa.shape[0] * self.pitch_mm[0]

    @property
    def width_mm(self) -> float:
        return self.kpa.shape[1] * self.pitch_mm[1]

    def mat_mm(self, along_mm: float, across_mm: float) -> tuple[float, float]:
        """Mat (x, y) in mm of a point ``along_mm`` from the head end and ``across_mm`` from the right edge."""
        return (along_mm, across_mm) if self.transposed else (across_mm, along_mm)

    def view_mm(self, x_mm: float, y_mm: float) -> tuple[float, float]:
        """(along, across) in the view of the mat point (x, y)."""
        return (x_mm, y_mm) if self.transposed else (y_mm, x_mm)

    def cell_centre_mm(self, row: int, col: int) -> tuple[float, float]:
        """(along, across) of a view cell's centre."""
        return (row + 0.5) * self.pitch_mm[0], (col + 0.5) * self.pitch_mm[1]


def is_bed(grid: PixelGrid) -> bool:
    """Whether the grid's mat is long enough for a body."""
    return max(grid.width_mm, grid.height_mm) >= BED_MIN_LENGTH_MM


def body_view(pressure_kpa: np.ndarray, grid: PixelGrid) -> BodyView:
    """The map on ``grid`` as the body sees it (NaN, off the sheet or unknown, read as no load).

    The bed layouts lie along x with the patient's left at +y (the virtual bed turns its scenes so), so their
    view is the transpose; a mat longer in y is already a view.
    """
    kpa = np.nan_to_num(np.asarray(pressure_kpa, dtype=float), nan=0.0)
    if kpa.shape != grid.shape:
        raise ValueError(f"a pressure map of shape {kpa.shape} for a pixel grid of shape {grid.shape}")
    w, h = grid.pixel_mm
    if grid.width_mm > grid.height_mm:
        return BodyView(kpa.T.copy(), (w, h), True)
    return BodyView(kpa, (h, w), False)
