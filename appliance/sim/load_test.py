"""The thesis's load test (chapter 6.3) simulated: a square load on the centre of the mat, stepped.

A flat square weight of area A is set on the middle of the membrane and the
pressure stepped, one reading a minute, up and back down. The weight sits on a
rigid platen, so the membrane under it stays flat (``platen`` of
:func:`~appliance.sim.mechanics.sheet_conductance`); the load is centred, so
the platen sinks without tilting. Each step gives the thesis's three measures
against the unloaded readings taken before the first step: visibility Q and
dV/V over all readings of the layout's default protocol
(:mod:`appliance.core.merit`), and the deformation, the platen's sink (the
membrane's deepest deflection plus what the platen sinks into its surface;
the thesis read it with a Vernier). The mat's play is carried from step to
step, so the order of the pressures matters.

The readings are the magnitudes the thesis's front end measured. Besides the
mat's own signal each carries a part the front end adds whatever the mat does
(common-mode feedthrough through an instrumentation amplifier built from 5 %
resistors, crosstalk between the multiplexer banks on veroboard), out of phase
with it, so the RMS converter adds the two in quadrature: ``front_end_floor``
times the rms unloaded reading. It matters only for the few readings the grid's
symmetry nearly nulls (16 of grid-4x4's 448 are under 2.5 % of the rms reading):
without it the first weights drive those through zero, each one's Q towards
-1, and the mean Q negative, which no table shows.

The liquid warms as the test goes on. The thesis's tables need it: every test
ends at zero pressure and zero deformation with Q and dV/V negative and
dV/V = 2 Q (-0.0033 and -0.0066 at 4 cm2), the signature of a uniform rise in
conductivity, a few tenths of a degree. It approaches its end as a first-order
lag, ``drift_c_per_step`` in the first step and ``drift_time_constant_steps``
steps of time constant (infinite for a steady warming): the 25 cm2 test, half
as long, ends about as warm as the others.

>>> rows = load_test(9.0, [0.0, 4.36, 0.0])
>>> [round(r.deformation_mm, 2) for r in rows][0], rows[1].visibility > 0
(0.0, True)
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np

from appliance.core.fem import build_fem_model
from appliance.core.forward import simulate
from appliance.core.layouts import RectSheet
from appliance.core.merit import fractional_change, visibility
from appliance.core.named_layouts import get_layout
from appliance.core.protocols import default_protocol
from appliance.errors import ModelInputInvalid
from appliance.sim.field import PressureField
from appliance.sim.mechanics import DEFAULT_PARAMETERS, MatParameters, conductance_on_model, sheet_conductance, \
    surface_sink_mm

AREA_RANGE_CM2 = (1.0, 36.0)
"""Load areas the test accepts: a 1 cm square up to a 6 cm one, which leaves the load clear of the
100 mm mat's clamped edge by more than the membrane's spreading length."""

PITCH_MM = 2.0
"""The mechanics grid: 50 x 50 cells on the thesis's mat, finer than the spreading length."""

# Fitted by benchmarks/sensor_model.py with the mat's parameters (sensor_model.md).
THESIS_FRONT_END_FLOOR = 0.01734
THESIS_DRIFT_C_PER_STEP = 0.1992
THESIS_DRIFT_TIME_CONSTANT_STEPS = 1.552


class LoadTestRow(NamedTuple):
    """One step of a load test."""

    pressure_kpa: float
    visibility: float
    dv_over_v: float
    deformation_mm: float


@functools.lru_cache(maxsize=4)
def _setup(layout_name: str, density: float):
    """The layout's FEM model and default protocol, built once per (layout, density)."""
    layout = get_layout(layout_name)
    return layout, build_fem_model(layout, density=density), default_protocol(layout)


def load_test(area_cm2: float, pressures_kpa, *, params: MatParameters = DEFAULT_PARAMETERS,
              layout: str = "grid-4x4", density: float = 1.0, temperature_c: float = 20.0,
              drift_c_per_step: float = THESIS_DRIFT_C_PER_STEP,
              drift_time_constant_steps: float = THESIS_DRIFT_TIME_CONSTANT_STEPS,
              front_end_floor: float = THESIS_FRONT_END_FLOOR) -> list[LoadTestRow]:
    """Simulate the thesis's test: a centred square load of ``area_cm2`` at each of ``pressures_kpa`` in turn.

    Parameters
    ----------
    area_cm2 : float
        Load area, 1 to 36 cm2.
    pressures_kpa : sequence of float
        Non-negative pressures, applied in the order given.
    params : MatParameters
    layout : str
        A layout name or TOML file with a rectangular sheet.
    density : float
        FEM mesh density.
    temperature_c : float
        Liquid temperature when the unloaded reference is read.
    drift_c_per_step : float
        Warming of the liquid in the first step (0 for an isothermal test).
    drift_time_constant_steps : float
        Time constant of the warming, in steps (``math.inf``: it goes on at the first step's rate).
    front_end_floor : float
        What the front end adds to every reading in quadrature, as a share of the rms
        unloaded reading (0 for the mat's readings alone).

    Returns
    -------
    list of LoadTestRow, one per pressure

    Raises
    ------
    ModelInputInvalid
        An area outside 1 to 36 cm2, no pressures, a negative or non-finite pressure, a
        pressure beyond the mat model's range, a temperature leaving its range, a
        time constant that is not positive or a floor that is negative.
    """
    pressures = _checked(area_cm2, pressures_kpa)
    if not drift_time_constant_steps > 0:
        raise ModelInputInvalid(f"the warming's time constant must be positive, got {drift_time_constant_steps!r} "
                                f"steps")
    if not (np.isfinite(front_end_floor) and front_end_floor >= 0):
        raise ModelInputInvalid(f"the front end's floor must be a non-negative share, got {front_end_floor!r}")
    mat, model, protocol = _setup(layout, float(density))
    if not isinstance(mat.sheet, RectSheet):
        raise ModelInputInvalid(f"the load test needs a rectangular mat; layout {mat.name!r} is a disc")
    width_mm, height_mm = mat.sheet.size_mm
    empty = PressureField.uniform(width_mm, height_mm, PITCH_MM)
    side_mm = 10.0 * math.sqrt(area_cm2)
    centre = (width_mm / 2, height_mm / 2)
    platen = empty.with_square_load(*centre, side_mm, 1.0).pressure_kpa >= 0.5
    state = None
    unloaded = _readings(model, protocol, sheet_conductance(params, empty, None, temperature_c)[0])
    floor = front_end_floor * math.sqrt(float(np.mean(unloaded**2)))
    reference = np.hypot(unloaded, floor)
    rows = []
    for step, pressure in enumerate(pressures):
        field = empty.with_square_load(*centre, side_mm, pressure)
        warming = drift_c_per_step * _elapsed(step, drift_time_constant_steps)
        conductance, deflection, state = sheet_conductance(params, field, state, temperature_c + warming,
                                                           platen=platen)
        volts = np.hypot(_readings(model, protocol, conductance), floor)
        sink = float(deflection.max() + surface_sink_mm(params, pressure))
        rows.append(LoadTestRow(float(pressure), visibility(volts, reference), fractional_change(volts, reference),
                                sink))
    return rows


def _elapsed(step: int, time_constant: float) -> float:
    """Steps' worth of warming at the first step's rate after ``step`` steps of a first-order lag."""
    return step if math.isinf(time_constant) else -time_constant * math.expm1(-step / time_constant)


def _readings(model, protocol, conductance: np.ndarray) -> np.ndarray:
    """The protocol's readings (V per A) over the mat with this conductance grid."""
    return simulate(model, conductance_on_model(model, conductance, PITCH_MM), protocol)


def _checked(area_cm2: float, pressures_kpa) -> np.ndarray:
    """The pressures as an array, or the input refused with what is wrong."""
    low, high = AREA_RANGE_CM2
    if not (np.isfinite(area_cm2) and low <= area_cm2 <= high):
        raise ModelInputInvalid(f"load area {float(area_cm2)!r} cm2 is outside the {low:g} to {high:g} cm2 the load "
                                f"test supports")
    pressures = np.asarray(pressures_kpa, dtype=float).ravel()
    if pressures.size == 0:
        raise ModelInputInvalid("a load test needs at least one pressure")
    bad = np.flatnonzero(~np.isfinite(pressures) | (pressures < 0))
    if bad.size:
        raise ModelInputInvalid(f"pressure {bad[0] + 1} of the load test is {float(pressures[bad[0]])!r} kPa; "
                                f"pressures must be finite and not negative")
    return pressures
