"""The benchmark scripts stay runnable: each one's pieces run on a small case and report sane numbers."""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"


def load(name):
    sys.path.insert(0, str(BENCHMARKS))
    try:
        spec = importlib.util.spec_from_file_location(f"bench_{name}", BENCHMARKS / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    finally:
        sys.path.remove(str(BENCHMARKS))


def test_forward_benchmark_phases():
    forward = load("forward")
    from appliance.core.layouts import get_layout

    nodes, build, assemble, factor, solve, total = forward.phase_times(get_layout("grid-4x4"), 0.5)
    assert 300 < nodes < 1500
    assert 0 < assemble < factor and 0 < solve and total < 1.0


@pytest.fixture(scope="module")
def chapter5():
    return load("thesis_chapter5")


def test_chapter5_sweep_and_literal_check_on_phantom_c(chapter5, monkeypatch):
    monkeypatch.setattr(chapter5, "CONTRASTS", np.array([1e-3, 1e3]))
    phantom = chapter5.Phantom("C", "network")
    q, dvv, q_subset, dvv_trimmed = chapter5.sweep(phantom)
    assert q.shape == (7, 2) and np.all(q[:, 0] > 0) and np.all(q[:, 1] < 0)
    assert np.abs(q - q_subset).max() < 1e-9
    assert phantom.nominal_area(10) == pytest.approx(100 / 256)
    dq, ddvv = chapter5.literal_check(phantom, contrasts=(1e-3,))
    assert dq < 1e-4


def test_chapter5_sensitivity_map_peaks_at_the_centre_for_c(chapter5):
    values = chapter5.sensitivity_map(chapter5.Phantom("C", "network"), n=5)
    assert values.shape == (5, 5) and values[2, 2] == np.nanmax(values)


def test_pressure_benchmark_helpers_and_a_small_backprojection_run(monkeypatch):
    pressure = load("pressure")
    from appliance.core.layouts import get_layout
    from appliance.core.pixels import pixel_grid
    from appliance.core.pressure_map import loaded_regions
    from appliance.sim.field import PressureField

    grid = pixel_grid(get_layout("grid-4x4"))
    field = PressureField.uniform(100, 100, 10.0).with_square_load(30, 60, 20, 8.0)
    averaged = pressure.pixel_average(field, grid)
    w, h = grid.pixel_mm
    assert averaged.sum() * w * h == pytest.approx(8.0 * 400)       # the force is kept
    regions = loaded_regions(averaged, grid)
    assert pressure.match_regions(regions, regions) == [0.0]
    assert pressure.match_regions(regions, []) == [float("inf")]
    loads = pressure.calibration_loads
    monkeypatch.setattr(pressure, "calibration_loads", lambda layout: loads(layout)[::7])
    results, notes, _ = pressure.single_load_part(1, ("backprojection",), lambda message: None)
    assert not notes
    rows = results["backprojection"]["rows"]
    assert [r["area"] for r in rows] == list(pressure.AREAS_CM2)
    assert all(np.isfinite(r["peak"]) and r["rmse"] >= 0 and r["seconds"] > 0 for r in rows)
    assert results["backprojection"]["iterate"] == "never" and pressure.iterate_for("greit") is None
    for r in rows:
        r["force"] = 1.0
    blur, lumps = pressure.blur_notes(results)
    assert blur.startswith("* backprojection") and lumps
    assert pressure.lumpy(6.2, 25) and pressure.lumpy(13.5, 16) and not pressure.lumpy(24.2, 4)
    from appliance.core.pressure import PressureCurve
    note = pressure.curve_note("greit", PressureCurve(np.array([0.0, 0.1, 0.2, 0.22]), np.array([0.0, 2.0, 5.0, 20.0])))
    assert "0.2 -> 5.0" in note and "1.10 times the change" in note


def test_mismatch_benchmark_runs_a_small_case(monkeypatch):
    mismatch = load("mismatch")
    from appliance.core.layouts import get_layout
    from appliance.core.protocols import default_protocol

    monkeypatch.setattr(mismatch, "DRAWS", 1)
    monkeypatch.setattr(mismatch, "LOADS", 4)
    monkeypatch.setattr(mismatch, "TRUTH_DENSITY", 1.5)
    layout = get_layout("grid-4x4")
    protocol = default_protocol(layout)
    nominal, fitting = mismatch.models(layout, protocol)
    case = mismatch.CASES[4]                                  # the saline mat: contacts the readings determine
    result = mismatch.run_case(case, layout, protocol, nominal, fitting)
    assert all(0 <= result[key][0] < 5 for key in ("image_before", "image_after", "region_before", "region_after"))
    fit = result["fits"][0]
    assert fit["accepted"] and fit["determined"] >= 8 and abs(fit["sheet"] - 1) < 0.05
    row = mismatch.case_rows([(case, result)])[0]
    assert row[0] == case.name and row[1] == 4
