"""Pressure calibration: the monotone curve, temperature correction, files and their fit to a layout."""

import json

import numpy as np
import pytest

from appliance.core.named_layouts import get_layout
from appliance.calibration import FOOT_END, HEEL_SIDE_MM, foot_end_loads, foot_end_mask
from appliance.core.pixels import pixel_grid
from appliance.core.pressure import (PressureCalibration, PressureCurve, ZoneCurve, fit_pressure_curve,
                                     layout_fingerprint, load_pressure_calibration, matched_curve,
                                     save_pressure_calibration, temperature_corrected)
from appliance.errors import ConfigError, DataFileInvalid


def test_the_curve_is_monotone_through_zero_and_recovers_a_smooth_law(rng):
    change = rng.uniform(0, 0.4, 400)
    truth = 40 * change + 60 * change**2                       # a stiffening mat
    noisy = truth + rng.normal(0, 0.5, change.size)
    curve = fit_pressure_curve(change, noisy)
    assert curve.change[0] == 0 and curve.pressure[0] == 0
    assert np.all(np.diff(curve.change) > 0) and np.all(np.diff(curve.pressure) >= 0)
    probe = np.linspace(0.02, 0.38, 30)
    error = curve.pressure_kpa(-probe) - (40 * probe + 60 * probe**2)
    assert np.max(np.abs(error)) < 0.8, np.max(np.abs(error))


def test_pressures_the_data_cannot_tell_apart_are_interpolated_not_stepped():
    # three loads whose peak changes bunch together (a bottomed-out mat): their pressures pool
    # into one value at the block's mean change, and pixels below it rise to it gradually
    curve = fit_pressure_curve(np.array([1.0, 2.0, 2.9, 3.0, 3.1]), np.array([1.0, 2.0, 20.0, 3.0, 10.0]))
    assert curve.pressure_kpa(np.array([-2.5]))[0] == pytest.approx(6.5)
    assert curve.pressure_kpa(np.array([-3.0]))[0] == pytest.approx(11.0)
    assert np.all(np.diff(curve.change) > 0) and np.all(np.diff(curve.pressure) >= 0)


def test_a_matched_curve_reads_the_high_pressures_at_their_height_where_a_regression_pulls_them_down(rng):
    # pressures 0-20 kPa seen through a noisy change: the regression reads the highest pressures well below
    # their height; matching reads the map with the truth's spread, so the top of the map is the top of the truth
    truth = rng.uniform(0, 20, 20000)
    change = truth / 40 + rng.normal(0, 0.1, truth.size)
    regressed = fit_pressure_curve(change, truth).pressure_kpa(-change)
    matched = matched_curve(change, truth).pressure_kpa(-change)
    assert np.quantile(matched, 0.99) == pytest.approx(np.quantile(truth, 0.99), rel=0.03)
    assert np.quantile(regressed, 0.99) < 0.95 * np.quantile(truth, 0.99)
    top = truth > np.quantile(truth, 0.99)
    assert np.mean(matched[top]) > 1.05 * np.mean(regressed[top])
    assert np.all(np.diff(matched_curve(change, truth).pressure) >= 0)


def test_a_matched_curve_needs_a_pressure_for_each_change():
    with pytest.raises(ConfigError, match="3 changes and 2 pressures"):
        matched_curve(np.array([0.1, 0.2, 0.3]), np.array([1.0, 2.0]))


def test_rises_in_conductivity_and_nan_read_as_nothing_and_nan():
    curve = fit_pressure_curve(np.array([0, 0.1, 0.2]), np.array([0, 5.0, 10.0]))
    out = curve.pressure_kpa(np.array([0.3, 0.0, np.nan, -0.3]))
    assert out[0] == 0 and out[1] == 0 and np.isnan(out[2])
    assert out[3] == pytest.approx(15.0)                       # beyond the last knot: the last slope


def test_a_flat_field_divides_the_change_first():
    curve = fit_pressure_curve(np.array([0, 0.1, 0.2]), np.array([0, 5.0, 10.0]))
    image = np.full((2, 2), -0.1)
    flat = np.array([[1.0, 2.0], [0.5, 1.0]])
    assert np.allclose(curve.pressure_kpa(image, flat), [[5.0, 2.5], [10.0, 5.0]])


def test_temperature_correction_undoes_the_liquids_drift():
    volts = np.array([1.0, -2.0])
    warm = volts / (1 + 0.02 * 3)            # three degrees warmer conducts 6 % better, reads lower
    assert temperature_corrected(warm, 27.0, 24.0) == pytest.approx(volts, rel=2e-3)
    assert temperature_corrected(volts, None, 24.0).tolist() == volts.tolist()


def calibration(layout="grid-4x4"):
    curve = fit_pressure_curve(np.array([0, 0.1, 0.2]), np.array([0, 5.0, 10.0]))
    lay = get_layout(layout)
    return PressureCalibration(lay.name, layout_fingerprint(lay), "greit", (16, 16), curve, 24.0,
                               flat_field=np.ones((16, 16)), notes={"loads": 12})


def test_files_round_trip_exactly(tmp_path):
    path = tmp_path / "cal.json"
    original = calibration()
    save_pressure_calibration(path, original)
    back = load_pressure_calibration(path)
    assert back.curve.change.tolist() == original.curve.change.tolist()
    assert back.curve.pressure.tolist() == original.curve.pressure.tolist()
    assert back.pixels == (16, 16) and back.notes == {"loads": 12}
    back.check_fits(get_layout("grid-4x4"), "greit", (16, 16))


def test_a_calibration_never_fits_another_layout_or_reconstruction():
    cal = calibration()
    with pytest.raises(ConfigError, match="made for layout 'grid-4x4', not for 'square-16'"):
        cal.check_fits(get_layout("square-16"), "greit", (16, 16))
    with pytest.raises(ConfigError, match="gn-laplace"):
        cal.check_fits(get_layout("grid-4x4"), "gn-laplace", (16, 16))
    with pytest.raises(ConfigError, match="shape"):
        cal.pressure_kpa(np.zeros((8, 8)))


@pytest.mark.parametrize(("mutate", "message"), [
    (lambda d: d.pop("curve"), "missing or malformed"),
    (lambda d: d.update(format="other"), "is not a pressure calibration"),
    (lambda d: d["curve"].update(pressure_kpa=[0, 5, 4]), "the curve is not monotonic: it falls from 5 kPa"),
    (lambda d: d.update(flat_field=[[1.0]]), "flat field shape"),
    (lambda d: d.update(zones=[{"name": "foot-end", "mask": [[1]],
                                "curve": {"change": [0, 1], "pressure_kpa": [0, 2]}}]), "zone's mask does not match"),
    (lambda d: d.update(zones=[{"name": "foot-end", "mask": [[0] * 16] * 16,
                                "curve": {"change": [0, 1], "pressure_kpa": [1, 2]}}]), "zone foot-end must start at"),
])
def test_bad_calibration_files_are_refused_by_name(tmp_path, mutate, message):
    path = tmp_path / "cal.json"
    save_pressure_calibration(path, calibration())
    data = json.loads(path.read_text())
    mutate(data)
    path.write_text(json.dumps(data))
    with pytest.raises(DataFileInvalid, match=message):
        load_pressure_calibration(path)
    path.write_text("{not json")
    with pytest.raises(DataFileInvalid, match="not valid JSON"):
        load_pressure_calibration(path)


def test_a_zone_curve_reads_its_own_pixels_and_survives_the_file(tmp_path):
    mask = np.zeros((16, 16), dtype=bool)
    mask[:, 12:] = True
    zone = ZoneCurve(FOOT_END, mask, PressureCurve(np.array([0.0, 1.0]), np.array([0.0, 30.0])))
    original = PressureCalibration(**{**calibration().__dict__, "zones": (zone,)})
    image = -0.5 * np.ones((16, 16))
    plain = calibration().pressure_kpa(image)
    read = original.pressure_kpa(image)
    assert np.allclose(read[:, 12:], 15.0) and np.array_equal(read[:, :12], plain[:, :12])
    save_pressure_calibration(tmp_path / "cal.json", original)
    back = load_pressure_calibration(tmp_path / "cal.json")
    assert np.array_equal(back.pressure_kpa(image), read) and back.zones[0].name == FOOT_END


def test_heel_size_loads_go_to_the_foot_end_of_a_bed_only():
    bed = get_layout("grid-8x16")                      # 1900 mm along x
    loads = foot_end_loads(bed, (5.0,))
    assert len(loads) == 6 and all(l.zone == FOOT_END and l.side_mm == HEEL_SIDE_MM for l in loads)
    assert all(1900 - 350 <= l.x_mm <= 1900 - HEEL_SIDE_MM / 2 for l in loads)
    mask = foot_end_mask(bed, pixel_grid(bed))
    assert mask[:, -1].all() and not mask[:, :25].any()
    assert foot_end_loads(get_layout("grid-4x4")) == []


def test_the_shipped_calibration_is_plausible_and_a_flat_or_scaled_away_one_is_not():
    import dataclasses
    from pathlib import Path

    from appliance.core.pressure import KPA_PER_MMHG, check_plausible, implausible

    shipped = load_pressure_calibration(Path(__file__).parents[1] / "appliance/sim/calibrations/grid-16x32.json")
    assert implausible(shipped) is None
    change, pressure = shipped.curve.change, shipped.curve.pressure
    flat = dataclasses.replace(shipped, curve=PressureCurve(change, np.zeros_like(pressure)))
    assert implausible(flat) == "the curve is constant: it reads every change as 0 kPa"
    tiny = dataclasses.replace(shipped, curve=PressureCurve(change, pressure / 30))   # 100 mmHg read as about 3
    said = implausible(tiny)
    assert said.startswith("the curve reads a change of 1 (the liquid film's whole conductance) as ")
    read_mmhg = float(said.split(" as ")[1].split(" mmHg")[0])
    assert read_mmhg == pytest.approx(np.interp(1.0, change, pressure) / 30 / KPA_PER_MMHG, abs=0.01)
    assert read_mmhg < 40                                                   # below what a mat's curve reads
    with pytest.raises(ConfigError, match="bench.json is implausible: the curve reads a change of 1"):
        check_plausible(tiny, "bench.json")
