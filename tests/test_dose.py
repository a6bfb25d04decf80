"""Pressure-time dose: the curves' numbers, accumulation, recovery, persistence and refusals."""

import json
import math

import numpy as np
import pytest
from scipy.optimize import brentq

from appliance.alerts.dose import MIN_TOLERABLE_S, DoseMap, custom_curve, reswick_rogers_mmhg, tolerance_curve
from appliance.core.pressure import KPA_PER_MMHG
from appliance.core.pressure_map import HIGH_PRESSURE_KPA
from appliance.errors import ConfigError, CurveInvalid, DataFileInvalid


def frames_to_full(dose: DoseMap, kpa: float, limit_s: int) -> int:
    """Seconds of 1-s frames at a constant ``kpa`` until the dose reaches 1."""
    frame = np.full(dose.shape, kpa)
    for second in range(1, limit_s + 1):
        dose.update(frame, 1.0)
        if dose.dose.max() >= 1.0:
            return second
    raise AssertionError(f"dose {dose.dose.max()} after {limit_s} s")


def reswick_rogers_s(kpa: float) -> float:
    """The fit inverted by root finding, independent of the module's grid."""
    return 3600 * brentq(lambda h: reswick_rogers_mmhg(h) - kpa / KPA_PER_MMHG, 0.0, 24.0, xtol=1e-12)


def test_reswick_rogers_matches_the_fit_and_the_table():
    curve = tolerance_curve("reswick-rogers")
    for mmhg in (35, 50, 64, 120, 299, 555, 1000):
        assert curve.tolerable_s(mmhg * KPA_PER_MMHG) == pytest.approx(reswick_rogers_s(mmhg * KPA_PER_MMHG), abs=0.5)
    assert curve.tolerable_s(64 * KPA_PER_MMHG) / 3600 == pytest.approx(6.0, abs=0.02)   # table: 64 mmHg at 6 h
    assert curve.tolerable_s(2000 * KPA_PER_MMHG) == MIN_TOLERABLE_S                      # beyond P(0) = 1184 mmHg


def test_reswick_rogers_dose_reaches_one_at_the_tolerable_time():
    expected = reswick_rogers_s(8.0)
    assert 6.0 < expected / 3600 < 6.5                                                   # 60 mmHg: just beyond 6 h
    seconds = frames_to_full(DoseMap((1, 1), tolerance_curve("reswick-rogers")), 8.0, 8 * 3600)
    assert abs(seconds - expected) <= 1.0


def test_linder_ganz_dose_reaches_one_where_the_sigmoid_is_the_pressure():
    curve = tolerance_curve("linder-ganz")
    minutes = 90 + math.log(23 / (10 - 9) - 1) / 0.15
    assert curve.pressure_kpa(minutes) == pytest.approx(10.0)
    seconds = frames_to_full(DoseMap((1, 1), curve), 10.0, 3 * 3600)
    assert abs(seconds - 60 * minutes) <= 1.0


def test_linder_ganz_limits():
    curve = tolerance_curve("linder-ganz")
    assert np.isinf(curve.tolerable_s(np.array([9.0, 8.9, 5.0]))).all()                 # at or below C: never
    assert curve.tolerable_s(np.array([32.0, 50.0])).tolist() == [MIN_TOLERABLE_S] * 2  # at or above K + C
    assert curve.tolerable_s(240 * KPA_PER_MMHG) / 60 == pytest.approx(29.7, abs=0.1)   # table: ~30 min


def test_curves_fall_with_pressure():
    kpa = np.linspace(4.4, 200.0, 500)
    for name in ("reswick-rogers", "linder-ganz"):
        seconds = tolerance_curve(name).tolerable_s(kpa)
        assert (seconds[1:] <= seconds[:-1]).all(), name


def test_nothing_accumulates_at_or_below_the_floor_or_off_the_sheet():
    dose = DoseMap((1, 4), tolerance_curve("reswick-rogers"))
    for _ in range(3600):
        dose.update(np.array([[HIGH_PRESSURE_KPA, 2.0, 0.0, np.nan]]), 1.0)
    assert dose.dose.tolist() == [[0.0] * 4]


def test_the_floor_is_configurable():
    curve = tolerance_curve("reswick-rogers", floor_kpa=2.0)
    assert np.isfinite(curve.tolerable_s(3.0))
    dose = DoseMap((1, 1), curve)
    dose.update(np.array([[3.0]]), 60.0)
    assert dose.fraction(np.array([[True]])) > 0


def loaded_then_offloaded(recovery: str, offload_s: int) -> DoseMap:
    dose = DoseMap((1, 2), tolerance_curve("linder-ganz"), recovery=recovery)
    for _ in range(3600):
        dose.update(np.array([[12.0, 12.0]]), 1.0)
    for _ in range(offload_s):
        dose.update(np.array([[12.0, 1.0]]), 1.0)                                       # the right pixel offloaded
    return dose


def test_a_ten_minute_offload_does_not_reset_a_fifteen_minute_one_does():
    short = loaded_then_offloaded("reset", 10 * 60)
    left, right = short.dose[0]
    assert right == pytest.approx(3600 / tolerance_curve("linder-ganz").tolerable_s(12.0))
    assert left > right                                                                  # still loaded, still rising
    assert loaded_then_offloaded("reset", 15 * 60).dose[0, 1] == 0.0
    assert loaded_then_offloaded("reset", 15 * 60 - 1).dose[0, 1] > 0.0


def test_a_brief_offload_then_reload_restarts_the_relief_clock():
    dose = loaded_then_offloaded("reset", 10 * 60)
    before = dose.dose[0, 1]
    dose.update(np.array([[12.0, 12.0]]), 1.0)
    for _ in range(10 * 60):
        dose.update(np.array([[12.0, 1.0]]), 1.0)
    assert dose.dose[0, 1] > before


def test_decay_halves_in_relief_time_ln2_and_falls_to_1_over_e_in_relief_time():
    loaded = loaded_then_offloaded("decay", 0).dose[0, 1]
    assert loaded_then_offloaded("decay", 900).dose[0, 1] == pytest.approx(loaded / math.e)
    half = 900 * math.log(2)
    dose = loaded_then_offloaded("decay", 0)
    dose.update(np.array([[12.0, 1.0]]), half)
    assert dose.dose[0, 1] == pytest.approx(loaded / 2)


def test_unknown_pixels_neither_load_nor_relieve():
    dose = loaded_then_offloaded("reset", 10 * 60)
    before = dose.dose[0, 1]
    dose.update(np.array([[12.0, np.nan]]), 30 * 60.0)                                   # a gap, marked unknown
    assert dose.dose[0, 1] == before
    assert dose.relieved_s[0, 1] == 10 * 60
    for _ in range(5 * 60):
        dose.update(np.array([[12.0, 1.0]]), 1.0)
    assert dose.dose[0, 1] == 0.0


def test_fraction_is_the_highest_dose_in_the_region():
    dose = DoseMap((2, 2), tolerance_curve("linder-ganz"))
    dose.update(np.array([[12.0, 20.0], [1.0, np.nan]]), 600.0)
    d = dose.dose
    assert dose.fraction(np.array([[True, True], [False, False]])) == d[0, 1]
    assert dose.fraction(np.array([[True, False], [True, True]])) == d[0, 0]
    assert dose.fraction(np.zeros((2, 2), bool)) == 0.0
    with pytest.raises(ValueError, match="mask of shape"):
        dose.fraction(np.ones((3, 2), bool))


def test_state_round_trips_through_json_and_continues_identically():
    rng = np.random.default_rng(1)
    frames = rng.uniform(0.0, 15.0, (400, 4, 5))
    frames[:, 0, 0] = np.nan
    frames[150:, 1, :] = 1.0                                                             # a row offloaded mid-way
    for recovery in ("reset", "decay"):
        curve = tolerance_curve("reswick-rogers")
        a = DoseMap((4, 5), curve, relief_s=120.0, recovery=recovery)
        for f in frames[:200]:
            a.update(f, 1.5)
        b = DoseMap.from_state(json.loads(json.dumps(a.state())), curve)
        assert b.state() == a.state()
        for f in frames[200:]:
            a.update(f, 1.5)
            b.update(f, 1.5)
        assert np.array_equal(a.dose, b.dose) and np.array_equal(a.relieved_s, b.relieved_s)


def test_bad_state_is_refused():
    curve = tolerance_curve("reswick-rogers")
    state = DoseMap((2, 2), curve).state()
    with pytest.raises(DataFileInvalid, match="linder-ganz"):
        DoseMap.from_state(state, tolerance_curve("linder-ganz"))
    with pytest.raises(DataFileInvalid, match="'dose'"):
        DoseMap.from_state({**state, "dose": [[0.0, 1.0]]}, curve)
    with pytest.raises(DataFileInvalid, match="incomplete"):
        DoseMap.from_state({k: v for k, v in state.items() if k != "relieved_s"}, curve)


@pytest.mark.parametrize("dt", [0.0, -1.0, 3601.0, float("nan"), float("inf")])
def test_bad_dt_is_refused(dt):
    dose = DoseMap((1, 1), tolerance_curve("reswick-rogers"))
    with pytest.raises(ValueError, match=r"dt_s = .* must be positive and at most 3600"):
        dose.update(np.array([[8.0]]), dt)


def test_bad_configuration_is_refused():
    curve = tolerance_curve("reswick-rogers")
    with pytest.raises(ConfigError, match="recovery 'linear'"):
        DoseMap((1, 1), curve, recovery="linear")
    with pytest.raises(ConfigError, match="relief_kpa 5 is above"):
        DoseMap((1, 1), curve, relief_kpa=5.0)
    with pytest.raises(ValueError, match="shape"):
        DoseMap((1, 1), curve).update(np.zeros((2, 2)), 1.0)
    with pytest.raises(CurveInvalid, match="known: reswick-rogers, linder-ganz"):
        tolerance_curve("gefen")


def test_custom_curve_interpolates_its_points():
    curve = custom_curve([[60, 200], [120, 100], [240, 50]])
    assert curve.tolerable_s(np.array([100.0, 75.0]) * KPA_PER_MMHG) == pytest.approx([7200.0, 10800.0])
    assert curve.tolerable_s(40 * KPA_PER_MMHG) == pytest.approx(14400.0)               # below the points: longest
    assert curve.tolerable_s(400 * KPA_PER_MMHG) == pytest.approx(1800.0)               # above: same P*t as 1st point
    assert np.isinf(curve.tolerable_s(30 * KPA_PER_MMHG))                               # below the floor


@pytest.mark.parametrize("points, message", [
    ([[60, 200]], "at least 2"),
    ([[60, 200], [120, -5]], r"point 2 \(120 min, -5 mmHg\): .* positive"),
    ([[60, 200], [0, 100]], r"point 2 \(0 min, 100 mmHg\)"),
    ([[60, 200], [120, 100], [180, 150]], r"point 3 \(180 min, 150 mmHg\) does not follow point 2"),
    ([[60, 200], [60, 100]], r"point 2 \(60 min, 100 mmHg\) does not follow point 1"),
    ([[60, 200], [120, float("nan")]], r"point 2 .* finite"),
    ([[60, 200], [120]], r"point 2 \[120\] is not a \(minutes, mmHg\) pair"),
    ([[60, 200], ["two hours", 100]], "point 2 .* is not a"),
])
def test_bad_custom_curves_are_refused_naming_the_point(points, message):
    with pytest.raises(CurveInvalid, match=message):
        custom_curve(points)
