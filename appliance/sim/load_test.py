"""The thesis's load test (chapter 6.3) simulated: a square load on the centre of the mat, stepped.

A flat square weight of area A is set on the middle of the membrane and the
pressure stepped, one reading a minute, up and back down. The weight sits on a
rigid platen, so the membrane under it stays flat (``platen`` of
:func:`~appliance.sim.mechanics.sheet_conductance`); the load is centred, so
the platen sinks without tilting. Each step gives the
thesis's three measures against the unloaded readings taken before the first
step: visibility Q and dV/V over all readings of the layout's default protocol
(:mod:`appliance.core.merit`), and the deformation, the membrane's deepest
deflection (the thesis read it with a Vernier). The mat's play is carried from
step to step, so the order of the pressures matters.

The liquid warms by ``drift_c_per_step`` each step. The thesis's tables need it:
every test ends at zero pressure and zero deformation with Q and dV/V negative
and dV/V = 2 Q (-0.0033 and -0.0066 at 4 cm2), the signature of a uniform rise
in conductivity, about 0.6 % over 16 minutes, a few tenths of a degree.

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
from appliance.core.layouts import RectSheet, get_layout
from appliance.core.merit import fractional_change, visibility
from appliance.core.protocols import default_protocol
from appliance.errors import ModelInputInvalid
from appliance.sim.field import PressureField
from appliance.sim.mechanics import DEFAULT_PARAMETERS, MatParameters, conductance_on_model, sheet_conductance

AREA_RANGE_CM2 = (1.0, 36.0)
"""Load areas the test accepts: a 1 cm square up to a 6 cm one, which leaves the load clear of the
100 mm mat's clamped edge by more than the membrane's spreading length."""

PITCH_MM = 2.0
"""The mechanics grid: 50 x 50 cells on the thesis's mat, finer than the spreading length."""

# Fitted by benchmarks/sensor_model.py to the three tables' return-to-zero rows (sensor_model.md).
THESIS_DRIFT_C_PER_STEP = 0.02096


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
              drift_c_per_step: float = THESIS_DRIFT_C_PER_STEP) -> list[LoadTestRow]:
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
        Warming of the liquid between two steps (0 for an isothermal test).

    Returns
    -------
    list of LoadTestRow, one per pressure

    Raises
    ------
    ModelInputInvalid
        An area outside 1 to 36 cm2, no pressures, a negative or non-finite pressure, a
        pressure beyond the mat model's range, or a temperature leaving its range.
    """
    pressures = _checked(area_cm2, pressures_kpa)
    mat, model, protocol = _setup(layout, float(density))
    if not isinstance(mat.sheet, RectSheet):
        raise ModelInputInvalid(f"the load test needs a rectangular mat; layout {mat.name!r} is a disc")
    width_mm, height_mm = mat.sheet.size_mm
    empty = PressureField.uniform(width_mm, height_mm, PITCH_MM)
    side_mm = 10.0 * math.sqrt(area_cm2)
    centre = (width_mm / 2, height_mm / 2)
    platen = empty.with_square_load(*centre, side_mm, 1.0).pressure_kpa >= 0.5
    state = None
    reference = _readings(model, protocol, sheet_conductance(params, empty, None, temperature_c)[0])
    rows = []
    for step, pressure in enumerate(pressures):
        field = empty.with_square_load(*centre, side_mm, pressure)
        conductance, deflection, state = sheet_conductance(params, field, state,
                                                           temperature_c + drift_c_per_step * step, platen=platen)
        volts = _readings(model, protocol, conductance)
        rows.append(LoadTestRow(float(pressure), visibility(volts, reference), fractional_change(volts, reference),
                                float(deflection.max())))
    return rows


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
