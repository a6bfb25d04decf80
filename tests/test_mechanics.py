"""The mat's mechanics: deflection, volume, spreading, the base, temperature, the play, the seating, bad input."""

import dataclasses

import numpy as np
import pytest

from appliance.core.fem import build_fem_model
from appliance.core.named_layouts import get_layout
from appliance.errors import ModelInputInvalid
from appliance.sim import mechanics
from appliance.sim.field import PressureField
from appliance.sim.mechanics import (
    DEFAULT_PARAMETERS,
    conductance_on_model,
    membrane_operator,
    reservoir_volume_mm3,
    sheet_conductance,
    surface_sink_mm,
)

PITCH_MM = 2.0
EMPTY = PressureField.uniform(100.0, 100.0, PITCH_MM)
NO_PLAY = dataclasses.replace(DEFAULT_PARAMETERS, hysteresis=0.0)


def square(pressure_kpa, side_mm=30.0, x_mm=50.0, y_mm=50.0):
    return EMPTY.with_square_load(x_mm, y_mm, side_mm, pressure_kpa)


def platen_of(side_mm=30.0):
    return square(1.0, side_mm).pressure_kpa >= 0.5


def test_membrane_operator_is_symmetric_positive_definite():
    k = membrane_operator((6, 5), 2.0).toarray()
    assert np.allclose(k, k.T)
    assert np.linalg.eigvalsh(k).min() > 0


@pytest.mark.parametrize("platen", [False, True])
def test_deflection_grows_with_pressure(platen):
    mask = platen_of() if platen else None
    peaks = [sheet_conductance(NO_PLAY, square(p), platen=mask)[1].max() for p in (0.5, 1, 2, 4, 8, 16, 32)]
    assert np.all(np.diff(peaks) > 0), f"peak deflections {np.round(peaks, 3)} mm do not grow with pressure"


@pytest.mark.parametrize("reservoir", [(0.0, np.inf), (DEFAULT_PARAMETERS.reservoir_mm3_per_kpa, np.inf),
                                       (DEFAULT_PARAMETERS.reservoir_mm3_per_kpa, 500.0), (1e5, 1e4)])
@pytest.mark.parametrize("fields", [
    [square(5.0)],
    [square(20.0, side_mm=10.0, x_mm=20.0, y_mm=70.0)],
    [EMPTY.with_square_load(25, 25, 20, 8).with_square_load(70, 60, 30, 3)],
    [square(2.0), square(40.0), square(1.0)],
])
def test_volume_is_conserved(fields, reservoir):
    """What the membrane displaces from the sheet is what the reservoir takes at the liquid's pressure
    (nothing in a rigid cell)."""
    compliance, capacity = reservoir
    params = dataclasses.replace(DEFAULT_PARAMETERS, reservoir_mm3_per_kpa=compliance, reservoir_capacity_mm3=capacity)
    state = None
    for field in fields:
        platen = field.pressure_kpa >= 0.5 * field.peak_kpa
        _, w, state = sheet_conductance(params, field, state, platen=platen)
        displaced = w.sum() * PITCH_MM**2
        taken = reservoir_volume_mm3(params, state.liquid_pressure_kpa)
        assert taken <= capacity
        assert state.liquid_pressure_kpa > 0
        assert abs(displaced - taken) <= 1e-9 * np.abs(w).sum() * PITCH_MM**2, \
            f"displaced {displaced:.6g} mm^3, the reservoir took {taken:.6g} mm^3"


def test_a_reservoir_takes_liquid_the_membrane_would_lift():
    """The more the cell's margins give, the less the unloaded membrane lifts, at a lower liquid pressure."""
    lifts, pressures = [], []
    for reservoir in (0.0, 1e3, 1e4, 1e6):
        params = dataclasses.replace(NO_PLAY, reservoir_mm3_per_kpa=reservoir, reservoir_capacity_mm3=np.inf)
        _, w, state = sheet_conductance(params, square(5.0), platen=platen_of())
        lifts.append(-w.min())
        pressures.append(state.liquid_pressure_kpa)
    assert np.all(np.diff(lifts) < 0) and np.all(np.diff(pressures) < 0), f"lifts {lifts} mm at {pressures} kPa"
    assert lifts[-1] < 0.1 * lifts[0]


def test_a_full_reservoir_takes_no_more():
    """Its compliance near rest, its capacity beyond: a load that fills it lifts the membrane as a rigid
    cell would for the rest of its volume."""
    full = dataclasses.replace(NO_PLAY, reservoir_mm3_per_kpa=1e6, reservoir_capacity_mm3=300.0)
    volume, rate = reservoir_volume_mm3(full, 1e-6, slope=True)
    assert volume == pytest.approx(1.0, rel=1e-2) and rate == pytest.approx(1e6, rel=1e-2)
    assert reservoir_volume_mm3(full, 50.0) == pytest.approx(300.0, rel=1e-4)
    assert reservoir_volume_mm3(full, -50.0) == pytest.approx(-300.0, rel=1e-4)
    _, w, state = sheet_conductance(full, square(10.0), platen=platen_of())
    assert w.sum() * PITCH_MM**2 == pytest.approx(300.0, rel=1e-2), "the reservoir is full"
    assert w.min() < 0, "the rest lifts"


def test_without_a_reservoir_or_seating_the_mat_is_what_it_was_before_them():
    """A sealed sheet (no reservoir) behaves alike whatever capacity it is given, and its description
    (what a virtual mat's calibration is keyed on) leaves out the reservoir and the seating it does not have."""
    sealed = dataclasses.replace(NO_PLAY, reservoir_mm3_per_kpa=0.0, reservoir_capacity_mm3=np.inf, seating_mm=0.0)
    other = dataclasses.replace(sealed, reservoir_capacity_mm3=500.0, seating_kpa=3.0)
    fields = [square(5.0), square(20.0, side_mm=10.0, x_mm=20.0, y_mm=70.0), square(1.0)]
    state = other_state = None
    for field in fields:
        g, w, state = sheet_conductance(sealed, field, state)
        g2, w2, other_state = sheet_conductance(other, field, other_state)
        assert np.array_equal(g, g2) and np.array_equal(w, w2)
        assert abs(w.sum()) <= 1e-9 * np.abs(w).sum(), "a sealed sheet keeps its volume"
    assert sealed.description() == other.description()
    sealed_only = {"reservoir_mm3_per_kpa", "reservoir_capacity_mm3", "seating_mm", "seating_kpa"}
    assert not sealed_only & set(sealed.description())
    assert DEFAULT_PARAMETERS.description() == dataclasses.asdict(DEFAULT_PARAMETERS)


def test_a_load_spreads_beyond_its_footprint_and_lifts_the_rest():
    field = square(5.0, side_mm=20.0)
    _, w, _ = sheet_conductance(NO_PLAY, field)
    row = w[25]                                     # the row through the centre, cells 2 mm wide
    inside, just_outside = row[24], row[19]         # x = 49 mm; x = 39 mm, 1 mm beyond the footprint's edge
    assert just_outside > 0.3 * inside, f"{just_outside:.3f} mm just outside against {inside:.3f} mm under the load"
    assert w.min() < 0, "the displaced liquid must lift the membrane somewhere"
    assert w[0].max() < 0.1 * inside, "the membrane is clamped at the mat's edge"


@pytest.mark.parametrize("side_mm", [10.0, 30.0, 60.0])
def test_deflection_never_reaches_the_base(side_mm):
    soft = dataclasses.replace(DEFAULT_PARAMETERS, foundation_kpa_per_mm=0.001, tension_n_per_m=5.0)
    for params in (DEFAULT_PARAMETERS, soft):
        g, w, _ = sheet_conductance(params, square(params.max_pressure_kpa, side_mm), platen=platen_of(side_mm))
        assert w.max() < params.rest_depth_mm, f"deflection {w.max():.4f} mm reaches the {params.rest_depth_mm} mm base"
        assert g.min() > 0


def test_conductance_scales_with_temperature_by_the_coefficient():
    field = square(6.0)
    g20, w20, _ = sheet_conductance(DEFAULT_PARAMETERS, field, temperature_c=20.0)
    g35, w35, _ = sheet_conductance(DEFAULT_PARAMETERS, field, temperature_c=35.0)
    assert np.array_equal(w20, w35), "temperature must not move the membrane"
    expected = 1 + DEFAULT_PARAMETERS.temperature_coefficient_per_c * 15.0
    assert np.allclose(g35 / g20, expected, rtol=1e-12)
    depth_m = (DEFAULT_PARAMETERS.rest_depth_mm - w20) * 1e-3
    assert np.allclose(g20, DEFAULT_PARAMETERS.conductivity_s_per_m * depth_m, rtol=1e-12)


def test_play_makes_falling_pressure_read_deeper_and_returns_to_rest():
    """As the thesis's tables: the decreasing branch lies a little above the increasing one."""
    pressures = [0.0, 2.0, 4.0, 8.0, 12.0, 8.0, 4.0, 2.0, 0.0]
    mask, state, peaks = platen_of(), None, []
    for p in pressures:
        _, w, state = sheet_conductance(DEFAULT_PARAMETERS, square(p), state, platen=mask)
        peaks.append(w.max())
    up, down = np.array(peaks[1:4]), np.array(peaks[5:8][::-1])
    assert np.all(down > up), f"decreasing {np.round(down, 4)} mm not above increasing {np.round(up, 4)} mm"
    assert np.all(down - up < 0.05 * up), "the play is slight"
    assert peaks[-1] == 0.0 and not state.effective_pressure_kpa.any(), "back at zero pressure the mat is at rest"


def test_the_seating_adds_to_a_contact_sink_but_moves_no_liquid():
    """What a platen sinks into the surface shows on a gauge, not in the liquid."""
    pressures = np.array([0.0, 0.05, 0.1, 0.5, 2.0, 20.0])
    sink = surface_sink_mm(DEFAULT_PARAMETERS, pressures)
    assert sink[0] == 0.0 and np.all(np.diff(sink) > 0)
    assert sink[-1] == pytest.approx(DEFAULT_PARAMETERS.seating_mm, rel=1e-9)
    assert sink[3] > 0.99 * DEFAULT_PARAMETERS.seating_mm, "closed by the thesis's lightest weights"
    unseated = dataclasses.replace(DEFAULT_PARAMETERS, seating_mm=0.0)
    assert not surface_sink_mm(unseated, pressures).any()
    g, w, _ = sheet_conductance(DEFAULT_PARAMETERS, square(2.0), platen=platen_of())
    g0, w0, _ = sheet_conductance(unseated, square(2.0), platen=platen_of())
    assert np.array_equal(g, g0) and np.array_equal(w, w0)


@pytest.mark.parametrize(("before", "after"), [(False, False), (True, True), (False, True), (True, False)])
def test_a_warm_start_from_a_deep_press_gives_the_cold_answer(monkeypatch, before, after):
    """The last deflection only tells Newton where to start, however close to the base it pressed (a start
    once restarted every cell deeper than half the depth) and through a platen it was not solved with."""
    steps = []
    force = mechanics.foundation_force
    monkeypatch.setattr(mechanics, "foundation_force", lambda *args: (steps.append(1), force(*args))[1])
    _, w_start, state = sheet_conductance(NO_PLAY, square(30.0, x_mm=49.0), platen=platen_of() if before else None)
    d0 = NO_PLAY.rest_depth_mm
    assert d0 - w_start.max() < 1e-3, "the warm start must press the membrane nearly onto the base"
    field, platen = square(32.0), platen_of() if after else None
    steps.clear()
    g_warm, w_warm, warm = sheet_conductance(NO_PLAY, field, state, platen=platen)
    warm_steps = len(steps)
    steps.clear()
    g_cold, w_cold, cold = sheet_conductance(NO_PLAY, field, platen=platen)
    cold_steps = len(steps)
    assert np.abs(w_warm - w_cold).max() <= 1e-9 * np.abs(w_cold).max()
    assert np.abs(g_warm - g_cold).max() <= 1e-9 * g_cold.max()
    assert abs(warm.liquid_pressure_kpa - cold.liquid_pressure_kpa) <= 1e-9 * abs(cold.liquid_pressure_kpa)
    if before == after:
        assert warm_steps < cold_steps, f"a warm start took {warm_steps} Newton steps, a cold one {cold_steps}"


@pytest.mark.parametrize(("change", "message"), [
    ({"rest_depth_mm": 0.0}, "rest_depth_mm must be positive"),
    ({"rest_depth_mm": -2.0}, "rest_depth_mm must be positive"),
    ({"conductivity_s_per_m": float("nan")}, "conductivity_s_per_m must be finite"),
    ({"hysteresis": 1.0}, "hysteresis must be in [0, 1)"),
    ({"slack_mm": -0.1}, "slack_mm must not be negative"),
    ({"contact_mm": 10.0}, "must be below rest_depth_mm"),
    ({"reservoir_mm3_per_kpa": -1.0}, "reservoir_mm3_per_kpa must not be negative"),
    ({"seating_mm": -0.1}, "seating_mm must not be negative"),
    ({"seating_kpa": 0.0}, "seating_kpa must be positive"),
    ({"reservoir_capacity_mm3": 0.0}, "reservoir_capacity_mm3 must be positive"),
    ({"reservoir_capacity_mm3": float("nan")}, "reservoir_capacity_mm3 must be finite"),
])
def test_bad_parameters_are_refused(change, message):
    with pytest.raises(ModelInputInvalid, match=message.replace("[", r"\[").replace(")", r"\)")):
        dataclasses.replace(DEFAULT_PARAMETERS, **change)


def test_bad_inputs_are_refused():
    limit = DEFAULT_PARAMETERS.max_pressure_kpa
    with pytest.raises(ModelInputInvalid, match="beyond the mat model's validity limit"):
        sheet_conductance(DEFAULT_PARAMETERS, square(limit * 1.5))
    with pytest.raises(ModelInputInvalid, match="outside the model's range"):
        sheet_conductance(DEFAULT_PARAMETERS, square(1.0), temperature_c=90.0)
    with pytest.raises(ModelInputInvalid, match="needs a PressureField"):
        sheet_conductance(DEFAULT_PARAMETERS, np.zeros((50, 50)))
    _, _, state = sheet_conductance(DEFAULT_PARAMETERS, square(1.0))
    with pytest.raises(ModelInputInvalid, match="mat state is for a"):
        sheet_conductance(DEFAULT_PARAMETERS, PressureField.uniform(100, 100, 4.0), state)
    with pytest.raises(ModelInputInvalid, match="boolean mask"):
        sheet_conductance(DEFAULT_PARAMETERS, square(1.0), platen=np.ones((10, 10), bool))


@pytest.fixture(scope="module")
def model():
    return build_fem_model(get_layout("grid-4x4"))


def test_conductance_on_model_samples_the_grid(model):
    xs, ys = EMPTY.centres_mm()
    ramp = 0.01 + 1e-4 * xs[None, :] + 2e-4 * ys[:, None]            # linear: bilinear sampling is exact
    sigma = conductance_on_model(model, ramp, PITCH_MM)
    x, y = np.clip(model.centroids_mm[:, 0], xs[0], xs[-1]), np.clip(model.centroids_mm[:, 1], ys[0], ys[-1])
    assert np.allclose(sigma, 0.01 + 1e-4 * x + 2e-4 * y, rtol=1e-12)
    assert np.allclose(conductance_on_model(model, np.full((50, 50), 0.02), PITCH_MM), 0.02)


def test_conductance_on_model_refuses_a_grid_too_small_or_not_positive(model):
    with pytest.raises(ModelInputInvalid, match="reaches beyond"):
        conductance_on_model(model, np.ones((20, 20)), PITCH_MM)
    with pytest.raises(ModelInputInvalid, match="positive"):
        conductance_on_model(model, np.zeros((50, 50)), PITCH_MM)
