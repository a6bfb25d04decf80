"""Layouts: built-in geometry, numbering, the TOML description and refused layouts."""

import math

import numpy as np
import pytest

from appliance.core.layout_files import layout_to_toml, load_layout
from appliance.core.layouts import DiscSheet, Layout, RectElectrode, RectSheet, SectorElectrode
from appliance.core.named_layouts import get_layout
from appliance.errors import LayoutInvalid


def test_grid_4x4_is_the_thesis_sensor_c():
    layout = get_layout("grid-4x4")
    assert layout.sheet == RectSheet(100.0, 100.0)
    centres = layout.centroids_mm()
    expected = [3.125, 34.375, 65.625, 96.875]
    assert np.allclose(centres[:, 0].reshape(4, 4), [expected] * 4)
    assert np.allclose(centres[:, 1].reshape(4, 4).T, [expected] * 4)
    assert all(e.width_mm == e.height_mm == 6.25 for e in layout.electrodes)


def test_square_16_numbers_clockwise_from_the_top_left_corner():
    layout = get_layout("square-16")
    c = layout.centroids_mm()
    cell = 100 / 17
    assert np.allclose(c[0], [cell / 2, cell / 2])          # top-left corner
    assert np.allclose(c[4], [100 - cell / 2, cell / 2])    # top-right corner
    assert np.allclose(c[8], [100 - cell / 2, 100 - cell / 2])
    assert np.allclose(c[12], [cell / 2, 100 - cell / 2])
    assert np.all(np.diff(c[:5, 0]) > 0) and np.all(np.diff(c[4:9, 1]) > 0)   # along the top, down the right


def test_circular_16_starts_at_the_top_and_runs_clockwise():
    layout = get_layout("circular-16")
    c = layout.centroids_mm()
    assert c[0][0] == pytest.approx(50) and c[0][1] < 10           # top
    assert c[4][0] > 90 and c[4][1] == pytest.approx(50)           # right, a quarter turn on
    angles = [e.angle_deg for e in layout.electrodes]
    assert np.allclose(np.diff(angles), 22.5)


def test_bed_grid_has_square_pitch_and_thesis_proportions():
    layout = get_layout("grid-8x16")
    assert layout.sheet.size_mm == (1900.0, 900.0)
    assert layout.grid_shape == (8, 16) and layout.n_electrodes == 128
    c = layout.centroids_mm()
    assert np.allclose(np.diff(c[:16, 0]), 125.0) and np.allclose(np.diff(c[::16, 1]), 125.0)
    assert layout.electrodes[0].width_mm == pytest.approx(25.0)


def test_grid_with_explicit_size():
    layout = get_layout("grid-3x5@400x800")
    assert layout.sheet.size_mm == (800.0, 400.0) and layout.n_electrodes == 15


@pytest.mark.parametrize("name", ["circular-16", "square-16", "grid-4x4", "grid-8x16"])
def test_toml_round_trip(name, tmp_path):
    layout = get_layout(name)
    path = tmp_path / "mat.toml"
    path.write_text(layout_to_toml(layout))
    assert load_layout(path) == layout
    assert get_layout(str(path)) == layout


def rect(n, x, y, w=6.0, h=6.0):
    return RectElectrode(n, x, y, w, h)


@pytest.mark.parametrize(("electrodes", "message"), [
    ((rect(1, 10, 10), rect(2, 13, 10)), "electrodes 1 and 2 overlap or touch"),
    ((rect(1, 10, 10), rect(2, 16, 10)), "electrodes 1 and 2 overlap or touch"),
    ((rect(1, 10, 10), rect(2, 98, 50)), "electrode 2 (centre 98, 50 mm, 6 x 6 mm) extends beyond the sheet's right"),
    ((rect(1, 10, -1), rect(2, 50, 50)), "extends beyond the sheet's top edge"),
    ((rect(1, 10, 10), rect(3, 50, 50)), "numbered 1..2 in order, got [1, 3]"),
    ((rect(1, 10, 10, w=0.0), rect(2, 50, 50)), "width and height must be positive"),
    ((rect(1, float("nan"), 10), rect(2, 50, 50)), "position and size must be finite"),
    ((SectorElectrode(1, 0, 10, 5), rect(2, 50, 50)), "sector electrodes belong on a disc sheet"),
])
def test_bad_rectangular_layouts_are_refused_by_name(electrodes, message):
    with pytest.raises(LayoutInvalid, match="mat") as err:
        Layout("mat", RectSheet(100, 100), electrodes)
    assert message in str(err.value)


@pytest.mark.parametrize(("electrodes", "message"), [
    ((SectorElectrode(1, 0, 10, 5), SectorElectrode(2, 9, 10, 5)), "electrodes 1 and 2 overlap or touch"),
    ((SectorElectrode(1, 355, 10, 5), SectorElectrode(2, 3, 10, 5)), "electrodes 1 and 2 overlap or touch"),
    ((SectorElectrode(1, 0, 10, 60), SectorElectrode(2, 90, 10, 5)), "depth must be positive and less than the radius"),
    ((SectorElectrode(1, 0, 400, 5),), "width must be between 0 and 360"),
    ((rect(1, 50, 50),), "a disc sheet takes sector electrodes"),
])
def test_bad_disc_layouts_are_refused_by_name(electrodes, message):
    with pytest.raises(LayoutInvalid) as err:
        Layout("disc", DiscSheet(50), electrodes)
    assert message in str(err.value)


def test_grid_numbering_must_be_row_major():
    electrodes = (rect(1, 10, 10), rect(2, 10, 50), rect(3, 50, 10), rect(4, 50, 50))
    with pytest.raises(LayoutInvalid, match="row-major from the top-left"):
        Layout("g", RectSheet(100, 100), electrodes, (2, 2))
    with pytest.raises(LayoutInvalid, match="a 3 x 2 grid needs 6 electrodes"):
        Layout("g", RectSheet(100, 100), electrodes, (3, 2))


def test_non_positive_sheet_is_refused():
    with pytest.raises(LayoutInvalid, match="sheet width_mm must be positive"):
        Layout("bad", RectSheet(0, 10), (rect(1, 1, 1),))


def test_unknown_layout_lists_the_choices():
    with pytest.raises(LayoutInvalid, match="unknown layout 'hexagon-7'.*circular-16"):
        get_layout("hexagon-7")


@pytest.mark.parametrize(("text", "message"), [
    ('name = "x"\n[sheet]\nshape = "rectangle"\nwidth_mm = 10\n', "[sheet]: 'height_mm' must be a number"),
    ('name = "x"\n[sheet]\nshape = "hexagon"\n', "shape must be 'rectangle' or 'disc'"),
    ('name = "x"\n[sheet]\nshape = "disc"\nradius_mm = 5\n', "the layout is missing 'electrodes'"),
    ('name = "x"\n[sheet]\nshape = "disc"\nradius_mm = 5\n[[electrodes]]\nnumber = 1\nshape = "sector"\n'
     'angle_deg = 0\nwidth_deg = 10\n', "[[electrodes]] entry 1: 'depth_mm' must be a number"),
    ("name = [", "is not valid TOML"),
])
def test_bad_layout_files_name_the_problem(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(LayoutInvalid) as err:
        load_layout(path)
    assert message in str(err.value) and str(path) in str(err.value)


def test_missing_layout_file(tmp_path):
    with pytest.raises(LayoutInvalid, match="does not exist"):
        get_layout(str(tmp_path / "none.toml"))


def test_sector_area_and_centroid():
    layout = get_layout("circular-16")
    e = layout.electrodes[4]
    r = 50.0
    assert layout.electrode_area_mm2(e) == pytest.approx(math.radians(e.width_deg) / 2 * (r**2 - (r - e.depth_mm) ** 2))
    x, y = e.centroid_mm(layout.sheet)
    assert x == pytest.approx(r + r - e.depth_mm / 2) and y == pytest.approx(r)
