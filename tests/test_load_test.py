"""The simulated load test: calibration against the thesis's tables, uncalibrated areas, the CLI."""

import csv
import io
from pathlib import Path

import numpy as np
import pytest

from appliance.cli import main
from appliance.errors import ModelInputInvalid
from appliance.sim.load_test import load_test

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "thesis"
needs_tables = pytest.mark.skipif(not (DATA / "sensor_response_4cm2.csv").exists(),
                                  reason=f"thesis tables not present at {DATA}")

# What the fitted defaults achieve (benchmarks/sensor_model.md): rows within 2 sd, less one (the two zero
# rows of a deformation table are all that 4 cm2 gets), and the median |relative error| over the loaded
# rows, plus a quarter. The low-pressure visibility rows are the model's known miss (see the report).
ROWS_WITHIN_2_SD = {
    (4, "visibility"): 4, (4, "dv_over_v"): 12, (4, "deformation_mm"): 1,
    (9, "visibility"): 13, (9, "dv_over_v"): 16, (9, "deformation_mm"): 8,
    (25, "visibility"): 8, (25, "dv_over_v"): 9, (25, "deformation_mm"): 5,
}
MEDIAN_RELATIVE_ERROR = {
    (4, "visibility"): 0.08, (4, "dv_over_v"): 0.03, (4, "deformation_mm"): 0.11,
    (9, "visibility"): 0.10, (9, "dv_over_v"): 0.08, (9, "deformation_mm"): 0.04,
    (25, "visibility"): 0.08, (25, "dv_over_v"): 0.07, (25, "deformation_mm"): 0.11,
}


@pytest.fixture(scope="module")
def calibration():
    from sensor_model import load_table, simulate_table, standardised  # benchmarks/, on the path by conftest

    out = {}
    for area in (4, 9, 25):
        rows = load_table(area)
        simulated = simulate_table(rows, area)
        out[area] = rows, simulated, standardised(rows, simulated)
    return out


@needs_tables
@pytest.mark.parametrize("key", sorted(ROWS_WITHIN_2_SD))
def test_model_tracks_the_thesis_tables(calibration, key):
    area, measure = key
    rows, simulated, residuals = calibration[area]
    within = int(np.sum(np.abs(residuals[measure]) <= 2))
    loaded = rows["pressure_kpa"] > 0
    relative = np.abs(simulated[measure][loaded] / rows[f"{measure}_mean"][loaded] - 1)
    median = float(np.median(relative))
    worst = int(np.argmax(np.abs(residuals[measure])))
    message = (f"{area} cm2 {measure}: {within} of {len(rows)} rows within 2 sd (need {ROWS_WITHIN_2_SD[key]}), "
               f"median relative error {median:.1%} (limit {MEDIAN_RELATIVE_ERROR[key]:.0%}); worst row {worst}: "
               f"{residuals[measure][worst]:+.1f} sd")
    assert within >= ROWS_WITHIN_2_SD[key] and median <= MEDIAN_RELATIVE_ERROR[key], message


def _response(area_cm2, pressures):
    rows = load_test(area_cm2, pressures, drift_c_per_step=0.0)
    return {name: np.array([getattr(r, name) for r in rows]) for name in rows[0]._fields}


def test_an_uncalibrated_area_lies_between_its_neighbours():
    """At equal pressure a larger load thins more of the sheet (dV/V grows with area); at equal weight
    a larger platen sinks less."""
    pressures = [0.0, 1.0, 2.0, 3.0]
    dvv = {a: _response(a, pressures)["dv_over_v"][1:] for a in (9, 16, 25)}
    assert np.all((dvv[9] < dvv[16]) & (dvv[16] < dvv[25])), f"dV/V at {pressures[1:]} kPa: {dvv}"
    weight_n = 1.0                                                    # about 100 g
    sink = {a: _response(a, [weight_n / (a * 1e-4) / 1e3])["deformation_mm"][0] for a in (1, 2, 4, 9, 16, 25)}
    assert sink[1] > sink[2] > sink[4], f"deformation under 1 N: {sink}"
    assert sink[9] > sink[16] > sink[25], f"deformation under 1 N: {sink}"


def test_order_of_pressures_matters_and_zero_returns_home():
    up_down = load_test(9.0, [0.0, 6.0, 3.0, 0.0], drift_c_per_step=0.0)
    up_only = load_test(9.0, [0.0, 3.0], drift_c_per_step=0.0)
    assert up_down[2].deformation_mm > up_only[1].deformation_mm
    assert up_down[3].deformation_mm == 0.0 and abs(up_down[3].visibility) < 1e-12


@pytest.mark.parametrize(("area", "pressures", "message"), [
    (0.5, [1.0], "outside the 1 to 36 cm2"),
    (40.0, [1.0], "outside the 1 to 36 cm2"),
    (9.0, [], "at least one pressure"),
    (9.0, [1.0, -2.0], "pressure 2 of the load test is -2.0 kPa"),
    (9.0, [float("nan")], "must be finite"),
    (9.0, [80.0], "validity limit"),
])
def test_bad_load_tests_are_refused(area, pressures, message):
    with pytest.raises(ModelInputInvalid, match=message):
        load_test(area, pressures)


def test_cli_load_test_prints_one_csv_row_per_pressure(capsys):
    code = main(["sim", "load-test", "--layout", "grid-4x4", "--area-cm2", "9", "--pressures", "0,2.18,4.36,2.18,0"])
    assert code == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert list(rows[0]) == ["pressure_kpa", "visibility", "dv_over_v", "deformation_mm"]
    expected = load_test(9.0, [0, 2.18, 4.36, 2.18, 0])
    assert [float(r["pressure_kpa"]) for r in rows] == [0, 2.18, 4.36, 2.18, 0]
    for row, want in zip(rows, expected):
        for name in ("visibility", "dv_over_v", "deformation_mm"):
            assert float(row[name]) == pytest.approx(getattr(want, name), rel=1e-5, abs=1e-9)


@pytest.mark.parametrize(("args", "message"), [
    (["--area-cm2", "0.5", "--pressures", "1"], "outside the 1 to 36 cm2"),
    (["--area-cm2", "9", "--pressures", "1,-2"], "must be finite and not negative"),
    (["--area-cm2", "9", "--pressures", "1,abc"], "--pressures takes numbers"),
    (["--area-cm2", "9", "--pressures", "100"], "validity limit"),
])
def test_cli_load_test_refuses_bad_input(capsys, args, message):
    assert main(["sim", "load-test", *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("appliance: error:") and message in err and err.count("\n") == 1, err
