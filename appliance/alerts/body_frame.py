"""Where a point of a map lies on the body: the body frame fitted to the map's contact.

A site is named from where it lies on the body, never from its distance to the mat's end (a patient slid
20 cm down the bed keeps the same sacrum), so each map gets its own frame (:func:`fit_body_frame`):

- contact: cells at or above ``CONTACT_KPA`` (5 mmHg), without specks (a lone touched cell);
- axis: the long principal axis of the trunk's contact (head to hips, the upper ``TRUNK_END`` of it,
  opened by 2 x 2 cells so that one-cell streaks and thin arms do not steer it): the one part that
  stays straight in every lying posture; its turn is kept within +/-12 degrees;
- head: the first contact along that axis, ``HEAD_GAP`` of the body length below the top of the head;
- length: the contact's extent along the axis over ``EXTENT_SHARE`` of the body length. Side-lying knees
  are drawn up, so there the length is at least the head-to-pelvis distance (the pelvis being the
  heaviest stretch of the trunk and legs) over ``PELVIS_AT``.

:func:`body_coordinates` gives points as (s, u): fractions of that length from the top of the head, and
across towards +across. Lying on the back, legs lie swung or splayed off the trunk's line and the trunk
itself may bend, so there ``u`` is measured from a midline found on the map. Supine or with the head of the
bed raised it is the pelvis's (:func:`_pelvic_midline`): the sacrum is told from the buttocks by a few cm across
it, and the hand labels take the midline from the body as a whole, which a hand or forearm lying beside one
stretch of the trunk must not shift. Prone (no labels) it stays the middle of the contact's width at each ``s``.
On the PmatData training subjects the fitted length is 0.98-1.04 of the subject's height (sd 0.05-0.09).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import binary_opening, label

from appliance.alerts.anatomy import BodyView, posture_side
from appliance.core.pressure import KPA_PER_MMHG
from appliance.errors import ModelInputInvalid

CONTACT_KPA = 5.0 * KPA_PER_MMHG
"""Where the body touches the mat: well above a sensor's noise, below any lying body's load."""

HEAD_GAP, EXTENT_SHARE, PELVIS_AT, TRUNK_END = 0.02, 0.97, 0.49, 0.55
MAX_TILT_DEG = 12.0
MIDLINE_BAND = 0.04
"""Half the stretch of body (fraction of its length) whose contact gives the midline at a point (prone)."""

PELVIS_SEARCH, PELVIS_STEP, PELVIS_SPAN, PELVIS_HALF = (0.30, 0.70), 0.01, 0.045, 0.10
"""Lying on the back, the pelvis is the heaviest stretch (``PELVIS_SPAN`` each side of a point searched in
``PELVIS_SEARCH``, fractions of the body length), and the midline is the mean ``u`` of the contact within
``PELVIS_HALF`` of it. Chosen by the leave-one-subject-out study over the training subjects (site_table.py's
notes): the local midline gave 0.80 of the loaded spots right, the pelvic one 0.81-0.82 for halves of 0.08-0.20."""


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


def posture_frame(view: BodyView, posture: str) -> BodyFrame:
    """The body frame fitted for a lying ``posture`` (lying 60 or 90 degrees on a side, or curled up, the knees
    may be drawn up)."""
    side = posture_side(posture)
    return fit_body_frame(view, side_lying=side is not None and not posture.endswith("30"))


def body_coordinates(view: BodyView, posture: str, along_mm, across_mm,
                     frame: BodyFrame | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(s, u) of view points in the frame fitted for a lying ``posture`` (``frame``: that frame, if already
    fitted); on the back ``u`` is taken from the pelvis's midline (supine, inclined) or from the body's midline at
    each point's ``s`` (prone)."""
    frame = frame or posture_frame(view, posture)
    s, u = frame.body_fractions(along_mm, across_mm)
    if posture in ("supine", "inclined"):
        u = u - _pelvic_midline(view, frame)
    elif posture_side(posture) is None:
        u = u - _midline(view, frame, np.atleast_1d(s))
    return np.atleast_1d(s), np.atleast_1d(u)


def fit_body_frame(view: BodyView, *, side_lying: bool = False) -> BodyFrame:
    """The body frame fitted to the contact of ``view`` (see the module's notes); ``side_lying`` allows for
    drawn-up legs: the length is then at least what the pelvis's distance from the head implies."""
    kpa = np.asarray(view.kpa, dtype=float)
    contact = body_contact(kpa)
    rows = np.flatnonzero(contact.any(axis=1))
    if len(rows) == 0:
        raise ModelInputInvalid("no contact on the map: there is no body to fit")
    pitch_along, pitch_across = view.pitch_mm
    straight = binary_opening(contact, np.ones((2, 2), dtype=bool))
    straight[rows[0] + int(TRUNK_END * (rows[-1] - rows[0])) + 1:] = False
    if not straight.any():                  # no stretch two cells wide (a foot, a hand): the contact itself
        straight = contact
    along_cells, across_cells = np.nonzero(straight)
    angle, level = _principal_axis(along_cells, across_cells, view.pitch_mm)
    r, c = np.nonzero(contact)
    on_axis = BodyFrame(0.0, level, angle, 1.0)
    s = on_axis.body_fractions((r + 0.5) * pitch_along, (c + 0.5) * pitch_across)[0]
    first, last = s.min() - pitch_along / 2, s.max() + pitch_along / 2
    length = (last - first) / EXTENT_SHARE
    if side_lying:
        length = max(length, (_pelvis(s - first, kpa[r, c]) + length * HEAD_GAP) / PELVIS_AT)
    head = first - length * HEAD_GAP
    return BodyFrame(head * math.cos(angle), level + head * math.sin(angle), angle, float(length))


def body_contact(kpa: np.ndarray) -> np.ndarray:
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


def _midline(view: BodyView, frame: BodyFrame, s: np.ndarray) -> np.ndarray:
    """``u`` of the middle of the contact's width within ``MIDLINE_BAND`` of each ``s`` (opened by 2 x 2 cells,
    so that a streak does not widen it); 0 where nothing touches."""
    contact = binary_opening(body_contact(np.asarray(view.kpa, float)), np.ones((2, 2), dtype=bool))
    rows, cols = np.nonzero(contact)
    if len(rows) == 0:
        return np.zeros_like(s)
    cs, cu = frame.body_fractions((rows + 0.5) * view.pitch_mm[0], (cols + 0.5) * view.pitch_mm[1])
    order = np.argsort(cs)
    cs, cu = cs[order], np.append(cu[order], 0.0)         # the sentinel lets a window end at the last cell
    first = np.searchsorted(cs, s - MIDLINE_BAND, side="left")
    end = np.searchsorted(cs, s + MIDLINE_BAND, side="right")
    touched = end > first
    bounds = np.column_stack([first, end]).ravel()        # reduceat over each [first, end) window in turn
    low = np.minimum.reduceat(cu, bounds)[::2]
    high = np.maximum.reduceat(cu, bounds)[::2]
    return np.where(touched, 0.5 * (low + high), 0.0)


def _pelvic_midline(view: BodyView, frame: BodyFrame) -> float:
    """``u`` of the middle of the pelvis: the mean across the contact (opened by 2 x 2 cells, each cell counted once
    whatever its load) within ``PELVIS_HALF`` of the heaviest stretch of the body; 0 where nothing touches."""
    kpa = np.asarray(view.kpa, float)
    contact = binary_opening(body_contact(kpa), np.ones((2, 2), dtype=bool))
    rows, cols = np.nonzero(contact)
    if len(rows) == 0:
        return 0.0
    cs, cu = frame.body_fractions((rows + 0.5) * view.pitch_mm[0], (cols + 0.5) * view.pitch_mm[1])
    load = kpa[rows, cols]
    centres = np.arange(PELVIS_SEARCH[0], PELVIS_SEARCH[1], PELVIS_STEP)
    pelvis = centres[int(np.argmax([load[np.abs(cs - c) <= PELVIS_SPAN].sum() for c in centres]))]
    near = np.abs(cs - pelvis) <= PELVIS_HALF
    return float(cu[near].mean()) if near.any() else 0.0


def _pelvis(s: np.ndarray, weights: np.ndarray) -> float:
    """Distance (mm) from the first contact to the heaviest 15 cm of the body between 30 and 75 % of
    the contact."""
    extent = s.max()
    edges = np.arange(0.3 * extent, 0.75 * extent, 30.0)
    if len(edges) == 0:
        return 0.0
    loads = [weights[(s >= e - 75.0) & (s < e + 75.0)].sum() for e in edges]
    return float(edges[int(np.argmax(loads))])
