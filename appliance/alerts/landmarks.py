"""The landmarks a reader finds first on the map of a patient lying on the back, as the labelling convention does.

The hand labels (tests/data/site_labels/CONVENTION.md, "First, per map") name the back's sites by distances from
three landmarks, not from where a place lies in the body as a whole: the **midline** (the line through the head's
centre and the middle between the legs), the **shoulder level** (the top of the trunk's load) and the **sacral
peak** (the hottest spot on the midline in the pelvis). A sacrum is the load within 55 mm of the midline from 60 mm
above to 90 mm below that peak, whatever the patient's height or how far they slid. :func:`back_landmarks` finds
the three on a :class:`~appliance.alerts.anatomy.BodyView` as a reader does:

- the head is the blob of contact at the top nearest the chest's middle (a hand raised beside it is another blob);
  the legs are the two largest blobs of the contact's ``LEG_BAND`` above its bottom (one when crossed or together);
- a reader takes the midline from head and legs, and from the trunk's outline where crossed or swung legs would
  pull it aside (the notes of the labels say so), so each row's midline is the median of three: the head-to-legs
  line, the head's centre, and the middle of the contact's outline within ``OUTLINE_HALF_MM`` of the row, smoothed
  along the body (``MIDLINE_SMOOTH_MM``). Checked against the landmarks the readers wrote in their notes on the
  training subjects' maps (tests/test_landmarks.py): within 15 mm of the reader's midline at the sacral peak in 75 %
  of 52 maps (the head-to-legs line alone, or the pelvis's mean that the site table measures from, in about half);
- the shoulder level is the first row ``SHOULDER_GAP_MM`` or more below the head's centre whose contact within
  250 mm of the midline spans ``SHOULDER_WIDTH_MM``: within 60 mm of the reader's in 81 % of 70 maps;
- the sacral peak is the hottest cell within ``SACRAL_SEARCH_MM`` of the midline and ``PELVIS_REACH`` of the body's
  length from the pelvis, the heaviest stretch (``PELVIS_SPAN_MM`` each side, streaks left out) found in
  ``PELVIS_SEARCH`` of the contact's extent: within 45 mm of the reader's in 91 % of 64 maps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import binary_opening, label, maximum_filter1d, median_filter, minimum_filter1d

from appliance.alerts.anatomy import BodyView
from appliance.alerts.body_frame import body_contact

HEAD_BAND = 0.10
"""The head is sought in this share of the contact's extent from its top."""
HEAD_SHARE = 0.25
CHEST_BAND = (0.20, 0.45)
"""The head is the top band's blob nearest the middle of the contact's outline over this share of its extent
(shoulders to waist), among blobs at least ``HEAD_SHARE`` of the largest (a hand or a streak is smaller). Taking
instead the larger blob holding the top-most row put one training subject's head on a raised arm 300 mm aside.
Against the readers' notes on the training maps (tests/test_landmarks.py): midlines within 15 mm 71 -> 75 % of 52,
sacral peaks within 45 mm 88 -> 91 % of 64; loaded spots right (leave-one-subject-out) 0.824 -> 0.827."""
LEG_BAND = (0.22, 0.05)
"""The legs are the contact between these shares of its extent above its bottom (the feet's ends, splayed or
pointing, left out)."""
OUTLINE_HALF_MM = 60.0
MIDLINE_SMOOTH_MM = 270.0
"""The midline is the running median of its rows over this stretch: a reader draws one line, and a row whose
outline an arm widens must not bend it (the virtual body's ischia were named beside its sacrum where it did).
Over 90-330 mm, the same share of the training subjects' loaded spots right (leave-one-subject-out, 0.813-0.814)."""
SHOULDER_GAP_MM, SHOULDER_WIDTH_MM, SHOULDER_REACH_MM = 80.0, 250.0, 250.0
SACRAL_SEARCH_MM = 55.0
PELVIS_SEARCH, PELVIS_SPAN_MM, PELVIS_REACH = (0.35, 0.65), 75.0, 0.10
STREAK_CELLS = 3
"""The pelvis's load is weighed on the map under a median of this many cells square: a sensor streak one cell wide
(the readers' notes name them, a hot line down the spine or across a row) is no pelvis, and once took one training
subject's sacral peak 330 mm up the spine. Leave-one-subject-out over the training subjects: 0.850 -> 0.854 of the
loaded spots right, on the same maps read through the virtual bed 0.843 -> 0.846; the peak moves on that one map
only, and on no held-out map."""


@dataclass(frozen=True)
class BackLandmarks:
    """A back-lying map's landmarks: the midline's across (mm) at each row of the view, the along (mm) of the
    shoulder level and of the sacral peak, and the sacral peak's across (None where the map shows none)."""

    midline_mm: np.ndarray
    shoulder_mm: float | None
    sacral_peak_mm: float | None
    sacral_peak_across_mm: float | None = None

    def from_midline(self, view: BodyView) -> np.ndarray:
        """Each cell's distance (mm) from the midline, towards the patient's left positive."""
        return _from_midline(self.midline_mm, view)


def back_landmarks(view: BodyView, floor_kpa: float) -> BackLandmarks:
    """The landmarks of ``view`` (see the module's notes); the sacral peak is a cell at or above ``floor_kpa``.
    A view with no contact has a midline down its middle and neither level."""
    kpa = np.asarray(view.kpa, dtype=float)
    contact = body_contact(kpa)
    pitch_along, pitch_across = view.pitch_mm
    along = (np.arange(kpa.shape[0]) + 0.5) * pitch_along
    rows = np.flatnonzero(contact.any(axis=1))
    if len(rows) == 0:
        return BackLandmarks(np.full(kpa.shape[0], view.width_mm / 2), None, None)
    top, bottom = rows[0] * pitch_along, (rows[-1] + 1) * pitch_along
    outline = _outline_middle(contact, view)
    chest = (along >= top + CHEST_BAND[0] * (bottom - top)) & (along <= top + CHEST_BAND[1] * (bottom - top))
    chest_across = float(np.nanmedian(outline[chest])) if np.isfinite(outline[chest]).any() else view.width_mm / 2
    head_along, head_across = _head(contact, view, top + HEAD_BAND * (bottom - top), chest_across)
    legs = _legs(contact, view, bottom - LEG_BAND[0] * (bottom - top), bottom - LEG_BAND[1] * (bottom - top))
    if legs is None or legs[0] <= head_along:
        line = np.full_like(along, head_across)
    else:
        line = head_across + (legs[1] - head_across) * (along - head_along) / (legs[0] - head_along)
    midline = np.nanmedian(np.stack([line, np.full_like(along, head_across), outline]), axis=0)
    midline = median_filter(midline, size=2 * round(MIDLINE_SMOOTH_MM / (2 * pitch_along)) + 1, mode="nearest")
    u = _from_midline(midline, view)
    peak = _sacral_peak(kpa, contact, view, u, top, bottom, floor_kpa)
    return BackLandmarks(midline, _shoulder_level(contact, view, u, head_along), *(peak or (None, None)))


def _from_midline(midline_mm: np.ndarray, view: BodyView) -> np.ndarray:
    return (np.arange(view.shape[1]) + 0.5)[None, :] * view.pitch_mm[1] - midline_mm[:, None]


def _cells_mm(view: BodyView) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = np.indices(view.shape)
    return (rows + 0.5) * view.pitch_mm[0], (cols + 0.5) * view.pitch_mm[1]


def _head(contact: np.ndarray, view: BodyView, band_end_mm: float, chest_across: float) -> tuple[float, float]:
    """(along, across) of the centre of the head: of the top band's blobs at least ``HEAD_SHARE`` of the largest, the
    one nearest the chest's middle ``chest_across`` (an arm raised beside the head may be larger and reach as high);
    the band holds the top-most touched row however short the contact."""
    along, across = _cells_mm(view)
    first = np.flatnonzero(contact.any(axis=1))[0]
    band = contact & (along <= max(band_end_mm, along[first, 0]))
    blobs, n = label(band, structure=np.ones((3, 3)))
    sizes = np.bincount(blobs.ravel(), minlength=n + 1)
    sizes[0] = 0
    big = [k for k in range(1, n + 1) if sizes[k] >= HEAD_SHARE * sizes.max()]
    head = blobs == min(big, key=lambda k: abs(across[blobs == k].mean() - chest_across))
    return float(along[head].mean()), float(across[head].mean())


def _legs(contact: np.ndarray, view: BodyView, start_mm: float, end_mm: float) -> tuple[float, float] | None:
    """(along, across) of the middle between the legs: the mean of the centres of the two largest blobs of the
    band (a blob under a quarter of the largest is a foot or hand, not a leg); None where nothing lies."""
    along, across = _cells_mm(view)
    blobs, n = label(contact & (along >= start_mm) & (along <= end_mm), structure=np.ones((3, 3)))
    if n == 0:
        return None
    sizes = np.bincount(blobs.ravel(), minlength=n + 1)
    sizes[0] = 0
    legs = [k for k in np.argsort(-sizes)[:2] if sizes[k] >= max(3, 0.25 * sizes.max())]
    if not legs:
        return None
    return (float(np.mean([along[blobs == k].mean() for k in legs])),
            float(np.mean([across[blobs == k].mean() for k in legs])))


def _outline_middle(contact: np.ndarray, view: BodyView) -> np.ndarray:
    """Per row, the middle of the contact's outline (opened by 2 x 2 cells) within ``OUTLINE_HALF_MM``; NaN where
    nothing touches."""
    opened = binary_opening(contact, np.ones((2, 2), dtype=bool))
    size = 2 * round(OUTLINE_HALF_MM / view.pitch_mm[0]) + 1
    first, last = _row_extents(opened)
    first = minimum_filter1d(first, size, mode="constant", cval=np.inf)
    last = maximum_filter1d(last, size, mode="constant", cval=-np.inf)
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(first), (0.5 * (first + last) + 0.5) * view.pitch_mm[1], np.nan)


def _row_extents(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row, the first and last column of ``cells`` that is set (inf and -inf for an empty row)."""
    cols = np.arange(cells.shape[1], dtype=float)
    return (np.where(cells, cols, np.inf).min(axis=1), np.where(cells, cols, -np.inf).max(axis=1))


def _shoulder_level(contact: np.ndarray, view: BodyView, u: np.ndarray, head_along: float) -> float | None:
    """Along (mm) of the top edge of the first row below the head wide enough to be the trunk."""
    first, last = _row_extents(contact & (np.abs(u) <= SHOULDER_REACH_MM))
    along = (np.arange(view.shape[0]) + 0.5) * view.pitch_mm[0]
    wide = (along >= head_along + SHOULDER_GAP_MM) & ((last - first + 1) * view.pitch_mm[1] >= SHOULDER_WIDTH_MM)
    return float(np.argmax(wide) * view.pitch_mm[0]) if wide.any() else None


def _sacral_peak(kpa: np.ndarray, contact: np.ndarray, view: BodyView, u: np.ndarray, top: float, bottom: float,
                 floor_kpa: float) -> tuple[float, float] | None:
    """(along, across) mm of the centre of the hottest cell near the midline in the pelvis."""
    along, _ = _cells_mm(view)
    length = bottom - top
    centres = np.arange(top + PELVIS_SEARCH[0] * length, top + PELVIS_SEARCH[1] * length, 10.0)
    if len(centres) == 0:
        return None
    row_along = along[:, 0]
    unstreaked = median_filter(kpa, size=STREAK_CELLS)
    row_load = np.concatenate([[0.0], np.cumsum(np.where(contact, unstreaked, 0.0).sum(axis=1))])
    low = np.searchsorted(row_along, centres - PELVIS_SPAN_MM, side="left")
    high = np.searchsorted(row_along, centres + PELVIS_SPAN_MM, side="right")
    pelvis = centres[int(np.argmax(row_load[high] - row_load[low]))]
    near = ((np.abs(u) <= SACRAL_SEARCH_MM) & (np.abs(along - pelvis) <= PELVIS_REACH * length)
            & (kpa >= floor_kpa))
    if not near.any():
        return None
    row, col = np.unravel_index(np.argmax(np.where(near, kpa, -np.inf)), kpa.shape)
    return float(along[row, col]), float((col + 0.5) * view.pitch_mm[1])
