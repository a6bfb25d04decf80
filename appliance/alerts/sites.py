"""Which bony prominence each loaded spot of a map lies over, for the posture the patient is in.

A pressure-injury alert is about tissue, not pixels: the sacrum of a patient slid
20 cm down the bed is still the sacrum. So the spots (local maxima at or above
``floor_kpa``) are named from where they lie in a body frame fitted to the map
(head end, axis, length), never from their distance to the mat's end.

The body frame (:func:`fit_body_frame`):

- contact: cells at or above ``CONTACT_KPA`` (5 mmHg), without specks (a lone cell
  below the floor);
- axis: the long principal axis of the trunk's contact (head to hips, the upper ``TRUNK_END`` of it,
  opened by 2 x 2 cells so that one-cell streaks and thin arms do not steer it): the one part that
  stays straight in every lying posture; its turn is kept within +/-12 degrees. Legs may lie swung
  off that line, so below the hips ``u`` is measured from the legs' own midline (supine family);
- head: the first contact along that axis, ``HEAD_GAP`` of the body length below
  the top of the head;
- length: the contact's extent along the axis over ``EXTENT_SHARE`` of the body
  length. Side-lying knees are drawn up, so there the length is at least the
  head-to-pelvis distance (the pelvis being the heaviest stretch of the trunk
  and legs) over ``PELVIS_AT``.

Geometry (fractions of the body length H from the top of the head, ``s``, and of H
across, ``u``, towards the patient's left as the supine patient lies):
the virtual body's table (:mod:`appliance.sim.body`: occiput 0.068, scapulae
0.215 at +/-0.072, sacrum 0.455, buttocks 0.50 at +/-0.062, thighs 0.63, calves
0.80, heels 0.962 at +/-0.055; 30-degree tilt: shoulder 0.19 and trochanter 0.50,
0.10 H to the down side) and Drillis & Contini's segment lengths (heights over H:
eye 0.936, shoulder 0.818, elbow 0.630, greater trochanter 0.530, knee 0.285,
ankle 0.039; widths: hips 0.191, shoulders 0.259), which give ear 0.07,
shoulder 0.18-0.19, elbow 0.37, trochanter 0.47-0.50, knee 0.715, malleolus 0.96.
Side-lying knees and ankles sit where the training maps put them (PmatData files
2, 3, 13, 14: straight-ish legs put knees at 0.66-0.72 and ankles at 0.88-0.95;
curled ones knees 0.55-0.62, 0.15-0.25 H forward of the trunk). A spot is named
after the nearest landmark in units of that landmark's spread (``_Landmark``)
if it lies within ``GATE`` spreads; landmarks that are no bony prominence
(back, buttock, thigh, calf, hand) leave it unnamed.

Left and right: the view's columns run towards a supine patient's left, so prone
sides are mirrored, and a patient lying on the left side faces +across (knees
point to the side lain on). Sitting on an edge (:func:`_ischia`): the two
heaviest spots near the edge sat on are the ischia; facing out from the
right-hand edge (across 0) the patient's left lies towards the foot end, from
the other edge towards the head end.

Checked on the PmatData training subjects (S1-S3, S5, S7-S10, all 17 files, middle
frame, 30 mm cells): the fitted length is 0.98-1.04 of the subject's height (sd 0.05-0.09);
supine heels lie at 0.88-0.95 of it (the recording's pitch is uncertain by +/-9 %), hence
the heel's 0.95 and wide spread. tests/test_sites.py asserts the order and sides.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import binary_opening, label, maximum_filter

from appliance.alerts.anatomy import BodyView, check_posture, posture_side
from appliance.calibration import BED_MIN_LENGTH_MM
from appliance.errors import ModelInputInvalid
from appliance.sim.field import KPA_PER_MMHG

FLOOR_KPA = 20.0 * KPA_PER_MMHG
"""Spots from 20 mmHg: a site approaching the 32 mmHg threshold is already tracked."""

CONTACT_KPA = 5.0 * KPA_PER_MMHG
"""Where the body touches the mat: well above a sensor's noise, below any lying body's load."""

SPOT_SPACING_MM = 70.0
"""Two maxima closer than this are one spot: under a heel (36 mm across) or the sacrum (60 mm)."""

HEAD_GAP, EXTENT_SHARE, PELVIS_AT, TRUNK_END = 0.02, 0.97, 0.49, 0.55
MAX_TILT_DEG = 12.0
GATE = 2.0


@dataclass(frozen=True)
class SiteReading:
    """One loaded spot: where it lies in the view (mm), its peak, and the site it is over (None: no
    bony prominence there)."""

    site: str | None
    along_mm: float
    across_mm: float
    peak_kpa: float


@dataclass(frozen=True)
class BodyFrame:
    """The body on the view: top of the head at (``head_along_mm``, ``head_across_mm``), axis turned
    ``angle_rad`` towards +across going to the feet, ``length_mm`` from head to heel."""

    head_along_mm: float
    head_across_mm: float
    angle_rad: float
    length_mm: float

    def body_fractions(self, along_mm, across_mm):
        """(s, u) of view points as fractions of the body length: s from the top of the head along the
        axis, u across it towards +across."""
        da, dc = np.asarray(along_mm) - self.head_along_mm, np.asarray(across_mm) - self.head_across_mm
        c, s = math.cos(self.angle_rad), math.sin(self.angle_rad)
        return (da * c + dc * s) / self.length_mm, (dc * c - da * s) / self.length_mm


@dataclass(frozen=True)
class _Landmark:
    """Where a site's spot is expected: centre (s, u) and spread (sd_s, sd_u), fractions of H.
    ``sites`` are given out in order of falling peak (a stacked pair: the down side first);
    empty for a loaded place that is no bony prominence."""

    sites: tuple[str, ...]
    s: float
    u: float
    sd_s: float
    sd_u: float


def _mark(site, s, u, sd_s=0.05, sd_u=0.05):
    return _Landmark((site,) if isinstance(site, str) else tuple(site), s, u, sd_s, sd_u)


def _pair(site, s, u, sd_s=0.05, sd_u=0.04):
    """Both sides' landmarks, the left at +u."""
    left, right = (f"{site}-left", f"{site}-right") if site else ((), ())
    return [_mark(left, s, u, sd_s, sd_u), _mark(right, s, -u, sd_s, sd_u)]


_SUPINE = (_mark("occiput", 0.068, 0.0, 0.05, 0.06), *_pair("scapula", 0.215, 0.075),
           _mark((), 0.33, 0.0, 0.06, 0.05), *_pair("elbow", 0.38, 0.18, 0.06, 0.05),
           _mark("sacrum", 0.46, 0.0, 0.045, 0.035), *_pair("", 0.51, 0.07, 0.04, 0.04),
           *_pair("", 0.63, 0.06, 0.06), *_pair("", 0.80, 0.05, 0.06), *_pair("", 0.60, 0.2, 0.08, 0.05),
           *_pair("heel", 0.95, 0.055, 0.05, 0.04))
_INCLINED = tuple(m for m in _SUPINE if not (not m.sites and m.s == 0.51)) + tuple(_pair("ischium", 0.51, 0.06))
_PRONE = (_mark("face", 0.07, 0.0, 0.05, 0.06), _mark("chest", 0.25, 0.0, 0.06, 0.07),
          *_pair("iliac-crest", 0.43, -0.075, 0.05, 0.04), *_pair("", 0.55, 0.07, 0.05, 0.04),
          *_pair("", 0.62, 0.06), *_pair("knee", 0.72, -0.05, 0.04, 0.04), *_pair("", 0.85, 0.05, 0.05),
          *_pair("toes", 0.99, -0.06, 0.04, 0.04))
# Lying on the left side, the front (and the drawn-up knees) towards +u; the right side mirrors these.
# Tilted, the whole body's load leans to the side lain on, so the fitted axis (which follows the load)
# lies TILT_LEAN towards it from the body's: the tilt's landmarks are moved by as much.
TILT_LEAN = 0.04
_LEFT_TILT_BODY = (_mark("occiput", 0.068, 0.01, 0.05, 0.06), _mark("shoulder-left", 0.19, 0.105, 0.04, 0.05),
              *_pair("scapula", 0.235, 0.055, 0.04, 0.035), _mark((), 0.33, 0.02, 0.06, 0.05),
              _mark("sacrum", 0.455, 0.015, 0.035, 0.035), _mark("trochanter-left", 0.50, 0.10, 0.04, 0.035),
              *_pair("", 0.51, 0.055, 0.035, 0.03), *_pair("", 0.63, 0.055, 0.06), *_pair("", 0.80, 0.05, 0.06),
              _mark("heel-left", 0.962, 0.052, 0.035, 0.035), _mark("heel-right", 0.962, -0.052, 0.035, 0.035))
_LEFT_TILT = tuple(_Landmark(m.sites, m.s, m.u - TILT_LEAN, m.sd_s, m.sd_u) for m in _LEFT_TILT_BODY)
_LEFT_SIDE = (_mark("ear-left", 0.06, 0.0, 0.045, 0.07), _mark("shoulder-left", 0.19, 0.0, 0.05, 0.07),
              _mark((), 0.33, 0.0, 0.06, 0.07), _mark((), 0.30, 0.12, 0.08, 0.06),
              _mark("trochanter-left", 0.49, 0.0, 0.05, 0.06), _mark((), 0.60, 0.03, 0.04, 0.07),
              _mark(("knee-left", "knee-right"), 0.69, 0.06, 0.05, 0.09), _mark((), 0.82, 0.03, 0.04, 0.07),
              _mark(("malleolus-left", "malleolus-right"), 0.93, 0.02, 0.05, 0.09))
_LEFT_FETAL = (_mark("ear-left", 0.06, 0.02, 0.045, 0.07), _mark("shoulder-left", 0.19, 0.0, 0.05, 0.07),
               _mark((), 0.33, 0.02, 0.06, 0.07), _mark("trochanter-left", 0.49, 0.0, 0.05, 0.06),
               _mark(("knee-left", "knee-right"), 0.58, 0.2, 0.06, 0.1), _mark((), 0.62, 0.07, 0.05, 0.05),
               _mark(("malleolus-left", "malleolus-right"), 0.82, 0.06, 0.08, 0.09))


def _mirrored(landmarks):
    """The same landmarks for the other side: u turned over, left and right swapped."""
    swap = {"left": "right", "right": "left"}

    def other(site):
        name, _, side = site.rpartition("-")
        return f"{name}-{swap[side]}" if side in swap else site
    return tuple(_Landmark(tuple(other(s) for s in m.sites), m.s, -m.u, m.sd_s, m.sd_u) for m in landmarks)


LANDMARKS = {"supine": _SUPINE, "inclined": _INCLINED, "prone": _PRONE,
             "left-30": _LEFT_TILT, "right-30": _mirrored(_LEFT_TILT),
             "left-60": _LEFT_SIDE, "right-60": _mirrored(_LEFT_SIDE),
             "left-90": _LEFT_SIDE, "right-90": _mirrored(_LEFT_SIDE),
             "fetal-left": _LEFT_FETAL, "fetal-right": _mirrored(_LEFT_FETAL)}
"""Every lying posture's landmarks (sitting on the edge and out of bed are not lying)."""


def locate_sites(view: BodyView, posture: str, *, floor_kpa: float = FLOOR_KPA) -> list[SiteReading]:
    """Every loaded spot of ``view`` (peak at or above ``floor_kpa``), each named with the site it lies over
    in ``posture``, highest first. Each site names one spot at most; out of bed there is none.

    Raises ConfigError for an unknown posture, ModelInputInvalid for a map that is no whole bed.
    """
    check_posture(posture)
    _check_map(view)
    if posture == "out-of-bed":
        return []
    spots = find_spots(view, floor_kpa)
    if not spots:
        return []
    along, across, peaks = (np.array(v) for v in zip(*spots))
    if posture == "sitting-edge":
        names = _ischia(view, along, across, peaks)
    else:
        frame = fit_body_frame(view, side_lying=posture_side(posture) is not None and posture[-2:] != "30")
        s, u = frame.body_fractions(along, across)
        if posture_side(posture) is None:
            u = u - _legs_offset(view, frame, s)
        names = _named(LANDMARKS[posture], s, u, peaks)
    return [SiteReading(n, float(a), float(c), float(p)) for n, a, c, p in zip(names, along, across, peaks)]


def _check_map(view: BodyView) -> None:
    kpa = np.asarray(view.kpa)
    if kpa.ndim != 2 or min(kpa.shape) < 3:
        raise ModelInputInvalid(f"a body view must be a 2-D map of at least 3 x 3 cells, got shape {kpa.shape}")
    if not np.all(np.isfinite(kpa)):
        raise ModelInputInvalid("a body view holds a non-finite pressure: read unknown cells as no load")
    if view.length_mm < BED_MIN_LENGTH_MM or view.length_mm < view.width_mm:
        raise ModelInputInvalid(f"a {view.length_mm:g} x {view.width_mm:g} mm view is no bed: sites need a "
                                f"mat at least {BED_MIN_LENGTH_MM:g} mm long, lying along the body")


def find_spots(view: BodyView, floor_kpa: float = FLOOR_KPA) -> list[tuple[float, float, float]]:
    """(along_mm, across_mm, peak_kpa) of every local maximum at or above ``floor_kpa``, highest first, placed
    to a fraction of a cell by a parabola through the peak and its neighbours."""
    kpa = np.asarray(view.kpa, dtype=float)
    size = [max(3, 2 * round(SPOT_SPACING_MM / (2 * p)) + 1) for p in view.pitch_mm]
    peak = (kpa >= floor_kpa) & (kpa == maximum_filter(kpa, size=size, mode="constant"))
    labels, n = label(peak, structure=np.ones((3, 3)))
    spots = []
    for k in range(1, n + 1):
        r, c = np.argwhere(labels == k)[0]
        spots.append(((r + 0.5 + _vertex(kpa[max(r - 1, 0):r + 2, c], r)) * view.pitch_mm[0],
                      (c + 0.5 + _vertex(kpa[r, max(c - 1, 0):c + 2], c)) * view.pitch_mm[1], float(kpa[r, c])))
    return sorted(spots, key=lambda spot: -spot[2])


def _vertex(line: np.ndarray, index: int) -> float:
    """Offset (cells, within +/-0.5) of the parabola's top through a peak and its two neighbours."""
    if len(line) < 3:
        return 0.0
    below, top, above = line
    curve = below - 2 * top + above
    return float(np.clip(0.5 * (below - above) / curve, -0.5, 0.5)) if curve < 0 else 0.0


def fit_body_frame(view: BodyView, *, side_lying: bool = False) -> BodyFrame:
    """The body frame fitted to the contact of ``view`` (see the module's notes); ``side_lying`` allows for
    drawn-up legs: the axis then follows the head, trunk and pelvis alone, and the length is at least what the
    pelvis's distance from the head implies."""
    kpa = np.asarray(view.kpa, dtype=float)
    contact = _contact(kpa)
    rows = np.flatnonzero(contact.any(axis=1))
    if len(rows) == 0:
        raise ModelInputInvalid("no contact on the map: there is no body to fit")
    pitch_along, pitch_across = view.pitch_mm
    straight = binary_opening(contact, np.ones((2, 2), dtype=bool))
    straight[rows[0] + int(TRUNK_END * (rows[-1] - rows[0])) + 1:] = False
    angle, level = _principal_axis(*np.nonzero(straight), view.pitch_mm)
    r, c = np.nonzero(contact)
    on_axis = BodyFrame(0.0, level, angle, 1.0)
    s = on_axis.body_fractions((r + 0.5) * pitch_along, (c + 0.5) * pitch_across)[0]
    first, last = s.min() - pitch_along / 2, s.max() + pitch_along / 2
    length = (last - first) / EXTENT_SHARE
    if side_lying:
        length = max(length, (_pelvis(s - first, kpa[r, c]) + length * HEAD_GAP) / PELVIS_AT)
    head = first - length * HEAD_GAP
    return BodyFrame(head * math.cos(angle), level + head * math.sin(angle), angle, float(length))


def _contact(kpa: np.ndarray) -> np.ndarray:
    """Cells the body touches; a lone touched cell (noise, a fingertip) is left out."""
    touched = kpa >= CONTACT_KPA
    labels, n = label(touched, structure=np.ones((3, 3)))
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    sizes[0] = 0
    return sizes[labels] > 1


def _principal_axis(rows: np.ndarray, cols: np.ndarray, pitch_mm: tuple[float, float]) -> tuple[float, float]:
    """(angle, across at along 0) of the long principal axis of the cells (each counted once, whatever its load:
    a heavy trochanter must not steer it), its turn kept within +/-MAX_TILT_DEG."""
    along, across = (rows + 0.5) * pitch_mm[0], (cols + 0.5) * pitch_mm[1]
    da, dc = along - along.mean(), across - across.mean()
    angle = 0.5 * math.atan2(2 * (da * dc).mean(), (da * da).mean() - (dc * dc).mean())
    angle = float(np.clip(angle, -math.radians(MAX_TILT_DEG), math.radians(MAX_TILT_DEG)))
    return angle, float(across.mean() - math.tan(angle) * along.mean())


def _legs_offset(view: BodyView, frame: BodyFrame, s: np.ndarray) -> np.ndarray:
    """How far (fractions of H, across) the legs' midline lies from the trunk's axis at each ``s``: legs may lie
    swung or splayed off the trunk's line, and a heel is told left from right by the legs' midline. Zero above
    the hips (``TRUNK_END``) and where no leg touches."""
    rows, cols = np.nonzero(binary_opening(_contact(np.asarray(view.kpa, float)), np.ones((2, 2), dtype=bool)))
    leg_s, leg_u = frame.body_fractions((rows + 0.5) * view.pitch_mm[0], (cols + 0.5) * view.pitch_mm[1])
    legs = leg_s > TRUNK_END
    if not legs.any() or np.ptp(leg_s[legs]) < 0.1:
        return np.zeros_like(s)
    slope, level = np.polyfit(leg_s[legs] - TRUNK_END, leg_u[legs], 1)
    return np.where(s > TRUNK_END, level + slope * (s - TRUNK_END), 0.0)


def _pelvis(s: np.ndarray, weights: np.ndarray) -> float:
    """Distance (mm) from the first contact to the heaviest 15 cm of the body between 30 and 75 % of
    the contact."""
    extent = s.max()
    edges = np.arange(0.3 * extent, 0.75 * extent, 30.0)
    if len(edges) == 0:
        return 0.0
    loads = [weights[(s >= e - 75.0) & (s < e + 75.0)].sum() for e in edges]
    return float(edges[int(np.argmax(loads))])


def _named(landmarks, s: np.ndarray, u: np.ndarray, peaks: np.ndarray) -> list[str | None]:
    """Each spot's site: the nearest landmark's within ``GATE`` spreads, its sites given to its spots from
    the highest down; spots beyond a landmark's sites, or at a landmark with none, stay unnamed."""
    centre = np.array([(m.s, m.u) for m in landmarks])
    spread = np.array([(m.sd_s, m.sd_u) for m in landmarks])
    d2 = (((s[:, None] - centre[None, :, 0]) / spread[None, :, 0]) ** 2
          + ((u[:, None] - centre[None, :, 1]) / spread[None, :, 1]) ** 2)
    nearest = np.argmin(d2, axis=1)
    names: list[str | None] = [None] * len(s)
    given = [0] * len(landmarks)
    for k in np.argsort(-peaks, kind="stable"):
        m = int(nearest[k])
        if d2[k, m] <= GATE**2 and given[m] < len(landmarks[m].sites):
            names[k] = landmarks[m].sites[given[m]]
            given[m] += 1
    return names


def _ischia(view: BodyView, along: np.ndarray, across: np.ndarray, peaks: np.ndarray) -> list[str | None]:
    """The heaviest spot and the next heaviest within 250 mm of it are the ischia (a lone spot stays unnamed:
    its side is unknown)."""
    names: list[str | None] = [None] * len(peaks)
    first = int(np.argmax(peaks))
    partners = [k for k in np.argsort(-peaks, kind="stable")
                if k != first and math.hypot(along[k] - along[first], across[k] - across[first]) <= 250.0]
    if partners:
        facing_right_edge = across[first] < view.width_mm / 2
        right, left = sorted((first, int(partners[0])), key=lambda k: along[k], reverse=not facing_right_edge)
        names[right], names[left] = "ischium-right", "ischium-left"
    return names
