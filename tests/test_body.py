"""The parametric body: exact force balance, clinical peak ranges, symmetry and refusals."""

import numpy as np
import pytest

from appliance.errors import ModelInputInvalid
from appliance.sim.body import (
    G_M_S2, POSTURES, SURFACES, MatGrid, Placement, Subject, body_field, outline_box_mm, site_peaks_mmhg, total_force_n,
)

SUBJECTS = [Subject(), Subject(50.0, 160.0), Subject(110.0, 185.0)]


@pytest.mark.parametrize("posture", POSTURES)
@pytest.mark.parametrize("subject", SUBJECTS, ids=lambda s: f"{s.weight_kg:g}kg")
def test_total_force_is_weight_times_g(posture, subject):
    field = body_field(subject, Placement(posture))
    expected = subject.weight_kg * G_M_S2
    assert abs(total_force_n(field) / expected - 1) < 1e-9, f"{total_force_n(field):.9g} N vs {expected:.9g} N"
    assert field.pressure_kpa.min() >= 0


GRIDS = [MatGrid(1000.0, 2000.0, 7.0), MatGrid(900.0, 1900.0, 50.0), MatGrid(850.0, 1800.0, 2.5)]


@pytest.mark.parametrize("grid", GRIDS, ids=["7mm", "50mm", "2.5mm"])
@pytest.mark.parametrize("surface", list(SURFACES))
def test_force_holds_on_any_grid_and_surface(grid, surface):
    field = body_field(Subject(), Placement("left-30", rotation_deg=4.0), grid, surface)
    assert field.pressure_kpa.shape == grid.shape
    assert abs(total_force_n(field) / (75.0 * G_M_S2) - 1) < 1e-9


# (posture, site, low, high, aimed at): clinical-anchors.md 2.5, standard foam, 75 kg / 175 cm
PEAK_RANGES = [
    ("supine", "sacrum", 35.0, 45.0, "40.2 (35.7-43.6) Hermans 2012"),
    ("supine", "heel-left", 45.0, 95.0, "45.5-59.2 foam, 93.9 hospital mattress"),
    ("supine", "heel-right", 45.0, 95.0, "45.5-59.2 foam, 93.9 hospital mattress"),
    ("supine", "occiput", 40.0, 60.0, "50.4 Hermans 2012"),
    ("left-30", "trochanter-left", 65.0, 95.0, "83.6 Thompson-Bishop 1992"),
    ("right-30", "trochanter-right", 65.0, 95.0, "83.6 Thompson-Bishop 1992"),
    ("left-30", "shoulder-left", 40.0, 75.0, "side-lying shoulder, above the supine back"),
    ("head-raised-45", "sacrum", 64.0, 100.0, "64-98.8 high Fowler's PPI, ~100 at 45 deg"),
    ("head-raised-30", "sacrum", 45.0, 75.0, "between supine and 45 deg"),
]


@pytest.mark.parametrize("posture, site, low, high, aim", PEAK_RANGES,
                         ids=[f"{p}-{s}" for p, s, *_ in PEAK_RANGES])
def test_site_peaks_land_in_clinical_ranges(posture, site, low, high, aim):
    peak = site_peaks_mmhg(Subject(), Placement(posture))[site]
    assert low <= peak <= high, f"{posture} {site} peak {peak:.1f} mmHg outside {low:g}-{high:g} (aimed at {aim})"


def test_left_tilt_mirrors_right_tilt():
    left = body_field(Subject(), Placement("left-30")).pressure_kpa
    right = body_field(Subject(), Placement("right-30")).pressure_kpa
    assert np.allclose(left, right[:, ::-1], rtol=1e-12, atol=1e-12)
    cols = np.arange(left.shape[1])
    assert (left.sum(0) * cols).sum() / left.sum() > left.shape[1] / 2, "left-30 must load +x, the patient's left"


def test_raising_the_head_loads_the_sacrum_more():
    sacrum = {p: site_peaks_mmhg(Subject(), Placement(p))["sacrum"]
              for p in ("supine", "head-raised-30", "head-raised-45")}
    assert sacrum["supine"] < sacrum["head-raised-30"] < sacrum["head-raised-45"], sacrum
    lateral = site_peaks_mmhg(Subject(), Placement("left-30"))["sacrum"]
    assert lateral < sacrum["supine"], f"a 30-degree tilt offloads the sacrum: {lateral:.1f} vs {sacrum['supine']:.1f}"


def test_surfaces_order_the_peaks():
    surfaces = ("pressure-reducing", "standard-foam", "firm")
    peaks = [body_field(Subject(), Placement(), surface=s).peak_kpa for s in surfaces]
    assert peaks[0] < peaks[1] < peaks[2], peaks


def test_position_rotation_and_height_move_the_body():
    base = outline_box_mm(Subject(), Placement(x_mm=450.0, y_mm=80.0))
    moved = outline_box_mm(Subject(), Placement(x_mm=480.0, y_mm=120.0))
    assert np.allclose(np.subtract(moved, base), [30.0, 40.0, 30.0, 40.0])
    tall = outline_box_mm(Subject(75.0, 185.0), Placement(x_mm=450.0, y_mm=80.0))
    assert tall[3] - tall[1] > base[3] - base[1] + 90, "contact length scales with height"
    field = body_field(Subject(), Placement(rotation_deg=5.0)).pressure_kpa
    feet = field[150:]
    cols = np.arange(field.shape[1]) + 0.5
    assert (feet.sum(0) * cols).sum() / feet.sum() > field.shape[1] / 2 + 5, "positive rotation swings the feet to +x"


@pytest.mark.parametrize("weight, height",
                         [(0.0, 175.0), (-70.0, 175.0), (75.0, 0.0), (75.0, -1.0), (float("nan"), 175.0)])
def test_refuses_non_positive_subject(weight, height):
    with pytest.raises(ModelInputInvalid, match="weight_kg|height_cm"):
        Subject(weight, height)


@pytest.mark.parametrize("subject, placement, grid", [
    (Subject(75.0, 200.0), Placement(), MatGrid()),
    (Subject(), Placement(x_mm=150.0), MatGrid()),
    (Subject(), Placement(y_mm=300.0), MatGrid()),
    (Subject(), Placement(rotation_deg=30.0), MatGrid()),
    (Subject(), Placement(), MatGrid(600.0, 1900.0, 10.0)),
], ids=["too-tall", "off-side", "off-foot", "rotated-off", "narrow-mat"])
def test_refuses_a_body_off_the_mat(subject, placement, grid):
    with pytest.raises(ModelInputInvalid, match="off the .* mat"):
        body_field(subject, placement, grid)


def test_refuses_unknown_posture_and_surface():
    with pytest.raises(ModelInputInvalid, match="prone"):
        Placement("prone")
    with pytest.raises(ModelInputInvalid, match="water-bed"):
        body_field(surface="water-bed")
