"""A parametric lying body: the pressure field a patient presses into the mat.

The body is a sum of smooth contact patches (super-Gaussians, flat-topped with
soft edges) at the sites that carry load: occiput, scapulae, back, sacrum,
buttocks, thighs, calves, heels and the arms beside the trunk; a 30-degree
lateral tilt adds the loaded side's shoulder and trochanter and the wedge
behind the back, and a raised head of bed moves trunk load onto the pelvis.
The whole field is scaled so that sum(p * cell area) = m g exactly. A field
limited to some ``sites`` (the heels alone on the mat, the rest of the body on
another surface) keeps those patches at their whole-body pressures, so its force
is their share of m g.

Peaks aimed at (75 kg, 175 cm, standard foam), clinical-anchors.md section 2.5:

- sacrum, supine ~40 mmHg (standard foam 40.2, range 35.7-43.6: Hermans 2012 [S42b]);
- heels ~55 mmHg (foam 45.5-59.2 [S42b]; standard hospital mattress 93.9:
  Thompson-Bishop 1992 [S41]);
- occiput ~50 mmHg (foam 50.4 [S42b]);
- trochanter, 30-degree tilt ~80 mmHg (standard mattress 83.6 [S41]);
- sacrum, head of bed 45 degrees ~85 mmHg (high Fowler's sacral PPI 64-98.8, median
  85.3 [S42e]; about 100 at 45 degrees [S42d]); 30 degrees ~60, between supine and 45.

Surfaces scale every peak (and shrink or widen the contact area so the force
stays m g): ``firm`` 1.5 (the standard hospital mattress of [S41] reads about
twice foam at the heel), ``pressure-reducing`` 0.75 (Tempur -20 to -30 %,
Defloor 2000 [S42c]). Sizes scale with height; peaks grow as the square root of
BMI (contact widens as the body sinks in). Peaks are cell averages, so they
fall slowly at coarse pitch. A body whose contact outline (where a patch falls
below 0.2 % of its peak) leaves the mat is refused: the mat would read less than
the weight, and a patient half off the bed is not this model's case.

Body frame: s along the axis from the top of the head, u towards the patient's
left, which lies at +x when the patient is supine, head at y = 0, seen from
above; ``left-30`` loads the left side.

>>> field = body_field(Subject(75.0, 175.0), Placement("supine"))
>>> field.pressure_kpa.shape, round(total_force_n(field) / (75.0 * G_M_S2), 12)
((190, 90), 1.0)
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace

import numpy as np

from appliance.errors import ModelInputInvalid
from appliance.sim.field import KPA_PER_MMHG, PressureField

G_M_S2 = 9.80665
POSTURES = ("supine", "left-30", "right-30", "head-raised-30", "head-raised-45")
SURFACES = {"standard-foam": 1.0, "firm": 1.5, "pressure-reducing": 0.75}
_REF_BMI = 75.0 / 1.75**2
_OUTLINE = 1.6          # patch radius (in semi-axes) beyond which it is below 0.2 % of its peak
_UPPER = ("occiput", "scapula-left", "scapula-right", "back")
_TO_PELVIS = {"sacrum": 0.45, "buttock-left": 0.175, "buttock-right": 0.175, "thigh-left": 0.1, "thigh-right": 0.1}


@dataclass(frozen=True)
class Subject:
    """The patient: weight (kg) and height (cm)."""

    weight_kg: float = 75.0
    height_cm: float = 175.0

    def __post_init__(self):
        for name in ("weight_kg", "height_cm"):
            if not (is_number(getattr(self, name)) and getattr(self, name) > 0):
                raise ModelInputInvalid(f"subject {name} must be a positive number, got {getattr(self, name)!r}")


def is_number(value) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool) \
        and bool(np.isfinite(value))


@dataclass(frozen=True)
class MatGrid:
    """The mat the field covers: ``width_mm`` across the bed, ``height_mm`` head to foot, square cells."""

    width_mm: float = 900.0
    height_mm: float = 1900.0
    pitch_mm: float = 10.0

    def __post_init__(self):
        for name in ("width_mm", "height_mm", "pitch_mm"):
            if not (is_number(getattr(self, name)) and getattr(self, name) > 0):
                raise ModelInputInvalid(f"mat {name} must be a positive number, got {getattr(self, name)!r}")
        if min(self.shape) < 1:
            raise ModelInputInvalid(f"a {self.pitch_mm:g} mm pitch leaves no cell on a "
                                    f"{self.width_mm:g} x {self.height_mm:g} mm mat")

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols)."""
        return round(self.height_mm / self.pitch_mm), round(self.width_mm / self.pitch_mm)

    def zeros(self) -> PressureField:
        return PressureField(np.zeros(self.shape), self.pitch_mm)


BED_GRID = MatGrid()
"""900 x 1900 mm at 10 mm: a standard mattress, head at y = 0."""


@dataclass(frozen=True)
class Placement:
    """Posture and position: body axis at ``x_mm``, top of the head at ``y_mm`` (None: centred on
    the mat), axis turned ``rotation_deg`` (positive swings the feet towards +x)."""

    posture: str = "supine"
    x_mm: float | None = None
    y_mm: float | None = None
    rotation_deg: float = 0.0

    def __post_init__(self):
        if self.posture not in POSTURES:
            raise ModelInputInvalid(f"unknown posture {self.posture!r}: use one of {', '.join(POSTURES)}")
        for name in ("x_mm", "y_mm", "rotation_deg"):
            value = getattr(self, name)
            if not (is_number(value) or (value is None and name != "rotation_deg")):
                raise ModelInputInvalid(f"placement {name} must be a finite number, got {value!r}")

    def on(self, grid: MatGrid, subject: Subject) -> Placement:
        """This placement with the defaults filled in for ``grid``."""
        x = grid.width_mm / 2 if self.x_mm is None else self.x_mm
        y = (grid.height_mm - 10 * subject.height_cm) / 2 if self.y_mm is None else self.y_mm
        return replace(self, x_mm=float(x), y_mm=float(y))


@dataclass(frozen=True)
class Patch:
    """One contact patch in the body frame: centre (s, u), semi-axes (a_u across, a_s along),
    peak pressure; lengths in mm or, in the tables below, as fractions of height."""

    site: str
    s: float
    u: float
    a_u: float
    a_s: float
    peak: float

    @property
    def force(self) -> float:
        """Integral of peak * exp(-r^4) over the plane (pi a b Gamma(3/2))."""
        return self.peak * math.pi * self.a_u * self.a_s * math.gamma(1.5)


def _pair(site, s, u, a_u, a_s, peak_left, peak_right=None):
    right = peak_left if peak_right is None else peak_right
    return [Patch(f"{site}-left", s, u, a_u, a_s, peak_left), Patch(f"{site}-right", s, -u, a_u, a_s, right)]


# fractions of height; peaks in mmHg before the exact force scaling
_SUPINE = [Patch("occiput", 0.068, 0.0, 0.032, 0.030, 50.0), *_pair("scapula", 0.215, 0.072, 0.040, 0.055, 28.0),
           Patch("back", 0.33, 0.0, 0.065, 0.085, 12.0), Patch("sacrum", 0.455, 0.0, 0.026, 0.034, 40.0),
           *_pair("buttock", 0.50, 0.062, 0.052, 0.055, 24.0), *_pair("thigh", 0.63, 0.058, 0.038, 0.085, 12.0),
           *_pair("calf", 0.80, 0.052, 0.028, 0.065, 17.0), *_pair("heel", 0.962, 0.055, 0.018, 0.018, 55.0),
           *_pair("arm", 0.38, 0.17, 0.025, 0.13, 9.0)]
_LEFT_30 = [Patch("occiput", 0.068, 0.012, 0.032, 0.030, 45.0),
            Patch("shoulder-left", 0.19, 0.105, 0.035, 0.05, 50.0),
            *_pair("scapula", 0.225, 0.06, 0.040, 0.055, 22.0, 8.0), Patch("back", 0.33, 0.02, 0.06, 0.085, 12.0),
            Patch("sacrum", 0.455, 0.015, 0.026, 0.034, 10.0),
            Patch("trochanter-left", 0.50, 0.10, 0.035, 0.045, 65.0),
            *_pair("buttock", 0.50, 0.055, 0.050, 0.055, 22.0, 8.0),
            *_pair("thigh", 0.63, 0.055, 0.038, 0.085, 16.0, 8.0),
            *_pair("calf", 0.80, 0.05, 0.028, 0.065, 20.0, 10.0),
            *_pair("heel", 0.962, 0.052, 0.018, 0.018, 55.0, 28.0),
            Patch("arm-left", 0.38, 0.16, 0.025, 0.13, 10.0), Patch("wedge", 0.33, -0.14, 0.05, 0.12, 6.0)]


def _mirrored(patches):
    swap = {"left": "right", "right": "left"}
    out = []
    for p in patches:
        head, _, side = p.site.rpartition("-")
        site = f"{head}-{swap[side]}" if side in swap else p.site
        out.append(replace(p, site=site, u=-p.u))
    return out


def _head_raised(angle_deg: float):
    """Supine with a share 0.75 sin^2(angle) of the upper body's force moved onto the pelvis."""
    share = 0.75 * math.sin(math.radians(angle_deg)) ** 2
    moved = share * sum(p.force for p in _SUPINE if p.site in _UPPER)
    out = []
    for p in _SUPINE:
        if p.site in _UPPER:
            p = replace(p, peak=p.peak * (1 - share))
        elif p.site in _TO_PELVIS:
            p = replace(p, peak=p.peak + _TO_PELVIS[p.site] * moved / (p.force / p.peak))
        out.append(p)
    return out


_TABLES = {"supine": _SUPINE, "left-30": _LEFT_30, "right-30": _mirrored(_LEFT_30),
           "head-raised-30": _head_raised(30.0), "head-raised-45": _head_raised(45.0)}
SITES = tuple(sorted({p.site for table in _TABLES.values() for p in table}))
"""Every anatomical site a posture loads; a posture loads only some of them."""


def _surface_factor(surface: str) -> float:
    if surface not in SURFACES:
        raise ModelInputInvalid(f"unknown surface {surface!r}: use one of {', '.join(SURFACES)}")
    return SURFACES[surface]


def body_patches(subject: Subject, posture: str, surface: str = "standard-foam") -> list[Patch]:
    """The posture's patches for ``subject`` in mm and kPa (before the exact force scaling)."""
    Placement(posture)
    stretch = 10 * subject.height_cm
    bulk = (subject.weight_kg / (subject.height_cm / 100) ** 2 / _REF_BMI) ** 0.25
    grow = stretch * bulk / math.sqrt(_surface_factor(surface))
    peak_kpa = KPA_PER_MMHG * _surface_factor(surface) * bulk**2
    return [Patch(p.site, p.s * stretch, p.u * stretch * bulk, p.a_u * grow, p.a_s * grow, p.peak * peak_kpa)
            for p in _TABLES[posture]]


def _frame(placement: Placement, x, y):
    """Body-frame (s, u) of mat points (x, y)."""
    t = math.radians(placement.rotation_deg)
    dx, dy = x - placement.x_mm, y - placement.y_mm
    return dx * math.sin(t) + dy * math.cos(t), dx * math.cos(t) - dy * math.sin(t)


def _to_mat(placement: Placement, s, u):
    t = math.radians(placement.rotation_deg)
    return placement.x_mm + s * math.sin(t) + u * math.cos(t), placement.y_mm + s * math.cos(t) - u * math.sin(t)


def outline_box_mm(subject: Subject, placement: Placement, grid: MatGrid = BED_GRID,
                   surface: str = "standard-foam") -> tuple[float, float, float, float]:
    """(x0, y0, x1, y1) of the body's contact outline on the mat, mm."""
    placement = placement.on(grid, subject)
    t = math.radians(placement.rotation_deg)
    boxes = []
    for p in body_patches(subject, placement.posture, surface):
        x, y = _to_mat(placement, p.s, p.u)
        hx = _OUTLINE * math.hypot(p.a_u * math.cos(t), p.a_s * math.sin(t))
        hy = _OUTLINE * math.hypot(p.a_u * math.sin(t), p.a_s * math.cos(t))
        boxes.append((x - hx, y - hy, x + hx, y + hy))
    b = np.array(boxes)
    return float(b[:, 0].min()), float(b[:, 1].min()), float(b[:, 2].max()), float(b[:, 3].max())


def body_field(subject: Subject = Subject(), placement: Placement = Placement(), grid: MatGrid = BED_GRID,
               surface: str = "standard-foam", sites: frozenset[str] | None = None) -> PressureField:
    """The field ``subject`` presses into the mat in ``placement``; total force m g exactly, or, with
    ``sites``, only those sites' patches at their whole-body pressures.

    Raises ModelInputInvalid when the body's whole outline leaves the mat or a site is unknown.
    """
    sites = check_sites(sites)
    placement = placement.on(grid, subject)
    x0, y0, x1, y1 = outline_box_mm(subject, placement, grid, surface)
    if x0 < 0 or y0 < 0 or x1 > grid.width_mm or y1 > grid.height_mm:
        raise ModelInputInvalid(
            f"a {subject.height_cm:g} cm, {subject.weight_kg:g} kg body {placement.posture} at "
            f"({placement.x_mm:g}, {placement.y_mm:g}) mm, turned {placement.rotation_deg:g} deg, reaches "
            f"x {x0:.0f} to {x1:.0f}, y {y0:.0f} to {y1:.0f} mm: off the {grid.width_mm:g} x {grid.height_mm:g} mm mat")
    return PressureField(_cached_field(subject, placement, grid, surface, sites).copy(), grid.pitch_mm)


def check_sites(sites) -> frozenset[str] | None:
    """``sites`` as a frozenset (None: the whole body); unknown names and an empty set are refused."""
    if sites is None:
        return None
    sites = frozenset(sites)
    if not sites:
        raise ModelInputInvalid(f"no site on the mat: give at least one of {', '.join(SITES)}")
    unknown = sorted(sites - set(SITES))
    if unknown:
        raise ModelInputInvalid(f"unknown site {unknown[0]!r}: use one of {', '.join(SITES)}")
    return sites


@functools.lru_cache(maxsize=64)
def _cached_field(subject, placement, grid, surface, sites) -> np.ndarray:
    rows, cols = grid.shape
    k = max(1, math.ceil(grid.pitch_mm / 5.0))         # sub-samples per cell side: cell averages
    sub = (np.arange(k) + 0.5) / k * grid.pitch_mm
    y = (np.arange(rows)[:, None] * grid.pitch_mm + sub[None, :]).ravel()
    x = (np.arange(cols)[:, None] * grid.pitch_mm + sub[None, :]).ravel()
    s, u = _frame(placement, x[None, :], y[:, None])
    fine, kept = np.zeros_like(s), np.zeros_like(s)
    for p in body_patches(subject, placement.posture, surface):
        r2 = ((u - p.u) / p.a_u) ** 2 + ((s - p.s) / p.a_s) ** 2
        patch = p.peak * np.exp(-(r2**2))
        fine += patch
        if sites is not None and p.site in sites:
            kept += patch
    whole = fine.reshape(rows, k, cols, k).mean(axis=(1, 3))
    scale = subject.weight_kg * G_M_S2 / (whole.sum() * grid.pitch_mm**2 * 1e-3)
    cells = (whole if sites is None else kept.reshape(rows, k, cols, k).mean(axis=(1, 3))) * scale
    cells.setflags(write=False)
    return cells


def total_force_n(field: PressureField) -> float:
    """Sum of pressure times cell area, N."""
    return float(field.pressure_kpa.sum() * field.pitch_mm**2 * 1e-3)


def site_peaks_mmhg(subject: Subject = Subject(), placement: Placement = Placement(), grid: MatGrid = BED_GRID,
                    surface: str = "standard-foam") -> dict[str, float]:
    """Highest cell of the field (mmHg) among those inside a site's patch ellipse where that patch
    contributes most."""
    field = body_field(subject, placement, grid, surface)
    placement = placement.on(grid, subject)
    xs, ys = field.centres_mm()
    s, u = _frame(placement, xs[None, :], ys[:, None])
    patches = body_patches(subject, placement.posture, surface)
    r2 = np.array([((u - p.u) / p.a_u) ** 2 + ((s - p.s) / p.a_s) ** 2 for p in patches])
    dominant = np.argmax([p.peak * np.exp(-(r**2)) for p, r in zip(patches, r2)], axis=0)
    peaks = {}
    for k, p in enumerate(patches):
        mine = (dominant == k) & (r2[k] <= 1.0)
        if mine.any():
            peaks[p.site] = float(field.pressure_kpa[mine].max() / KPA_PER_MMHG)
    return peaks
