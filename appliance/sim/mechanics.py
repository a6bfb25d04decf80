"""The mat's mechanics: pressure field -> membrane deflection -> liquid depth -> sheet conductance.

The thesis's sensor (chapter 6) is a layer of conductive liquid under a tensioned
rubber membrane, in a closed cell. A load pushes the membrane down; the liquid
under it thins and, being incompressible, goes where the cell gives: up under
the rest of the membrane, and into what lies outside the sensed sheet (the
cell's margins, its walls). EIT sees the sheet conductance, conductivity x
liquid depth, fall under the load and rise around it. On the pressure field's
grid of cells of side a (deflection w in mm, positive down):

    -T lap(w) + f(w) = p_eff - p_liquid,     a^2 sum(w) = R(p_liquid)

* T lap(w): the membrane's tension spreads a load beyond its footprint; the
  membrane is clamped at the mat's edge (w = 0 there).
* f(w): what carries the membrane besides the liquid's pressure, a Winkler bed
  k w. Over a bare liquid k is the liquid's own weight, rho g (lifting the
  membrane raises the column it holds up): the thesis's cell has nothing else,
  and its tables want nothing else. A stiffer bed (a mat designed for body
  pressures) has a larger k and may have an initial slack s,
  f = k (w - s tanh(w / s)). A contact barrier k c^2 (1 / (d0 - w) - 1 / d0 - w / d0^2)
  for w > 0 stiffens it without bound as the membrane nears the base: the
  deflection saturates below the rest depth d0 and the depth stays positive.
* p_liquid: the liquid's pressure rise, one value for the whole cell (Pascal's
  law), a Lagrange multiplier that makes the displaced volume reappear as the
  membrane lifts elsewhere and in a reservoir outside the sensed sheet (the
  cell's margins), which takes R(p) = C p / (1 + C |p| / V): C per kPa at
  first, never more than V (C = 0: a rigid cell, the sheet's volume conserved
  exactly). The lift
  comes from the membrane model itself: it is largest mid-way between the load
  and the clamped edge (the thesis's edge artefacts), and it grows faster once
  the reservoir is full (the thesis's large loads, whose "conductive medium is
  forced to the areas where no pressure is applied").
* p_eff: the applied pressure through a frictional play. The membrane and the
  load stick until the pressure has moved by a share h of itself, so a falling
  pressure acts as slightly more than it is and a rising one as slightly less
  (the decreasing branches of the tables lie a little above the increasing
  ones); the band shrinks to nothing at zero pressure, so the mat returns to
  rest. The play is held per cell in :class:`MatState`.

A rigid platen (the thesis's weights) is a set of cells that move as one plane:
they share three unknowns, its sink and two tilts. It also sinks into the
membrane's surface before it moves any liquid (:func:`surface_sink_mm`): every
thesis table's first weight sinks about 0.3 mm more than the rest of its branch
carries on, whatever its area, with no matching signal. The problem is the
minimum of a convex energy, solved by Newton's method on the bordered system;
each step's systems by conjugate gradients on a multigrid hierarchy made once for
the grid (:mod:`appliance.sim.multigrid`), or by a sparse factorisation each.

>>> from appliance.sim.field import PressureField
>>> field = PressureField.uniform(100, 100, 2.0).with_square_load(50, 50, 20, 9.81)
>>> conductance, deflection, state = sheet_conductance(DEFAULT_PARAMETERS, field)
>>> bool(deflection.max() < DEFAULT_PARAMETERS.rest_depth_mm)
True
>>> reservoir = reservoir_volume_mm3(DEFAULT_PARAMETERS, state.liquid_pressure_kpa)      # volume is conserved
>>> bool(abs(4.0 * deflection.sum() - reservoir) < 1e-9 * reservoir)
True
>>> round(float(conductance.min() / conductance.max()), 2)      # under the load, against the lifted edge
0.16
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.interpolate import RegularGridInterpolator

from appliance.core.forward import ForwardModel
from appliance.errors import ModelInputInvalid, SolverError
from appliance.sim.field import PressureField
from appliance.sim.multigrid import InexactSteps, MembraneHierarchy, dot

SOLVERS = ("multigrid", "direct")
"""How :func:`solve_deflection` solves a Newton step's systems."""

TEMPERATURE_RANGE_C = (0.0, 60.0)
"""Where a linear temperature coefficient describes saline and glycol mixtures well enough."""


@dataclass(frozen=True)
class MatParameters:
    """The mat's physical parameters; the defaults are fitted to the thesis (see ``DEFAULT_PARAMETERS``).

    Attributes
    ----------
    rest_depth_mm : float
        Liquid depth under the unloaded membrane, d0.
    conductivity_s_per_m : float
        Liquid conductivity at 20 C. The thesis gives "125 mS" for its ethylene
        glycol and saline; on the scale of its "100 mS" saline tank, the 10 mS/cm
        (1 S/m) saline of its other tanks and of the emulated sensor, that is
        1.25 S/m. Its Table 3.2.2.1 impedances give about 1.5 S/m on our FEM, and
        at 1.25 S/m and the fitted depth the largest reading at the thesis's
        2.5 mA limit is about 74 mV, 7.4 V after the smallest gain (100): where
        its AD536A (7 V rms) saturates, which is what set that limit. 125 mS/cm,
        half saturated brine, fits neither. Q and dV/V do not depend on it.
    temperature_coefficient_per_c : float
        Relative change of conductivity per degree C (0.02 for saline).
    tension_n_per_m : float
        Membrane tension T (N/m, which is kPa mm).
    foundation_kpa_per_mm : float
        Winkler stiffness k of what carries the membrane besides the liquid's
        pressure: the liquid's own weight, rho g = 0.0105 kPa/mm for glycol and
        saline (1.07 g/cm3), over a bare liquid as in the thesis's cell (not
        fitted: the tables leave anything from 0 to about 0.15 kPa/mm to the
        tension); a mat built on a spacer or foam has its own, far stiffer.
    slack_mm : float
        Initial slack s of the foundation; 0 for none (the thesis's cell: its
        easy first fraction of a millimetre is the surface's seating, which
        moves no liquid).
    contact_mm : float
        Length c of the contact barrier: its stiffness, k c^2 / gap^2, matches
        the foundation's when the gap to the base is down to c; with the
        liquid's weight as k it is the hard base (not fitted).
    hysteresis : float
        Relative width h of the frictional play on pressure, 0 <= h < 1.
    max_pressure_kpa : float
        Highest pressure accepted: 2.5 times the thesis's highest (19.6 kPa) and
        above seated interface pressures; small loads are on the base by then.
    reservoir_mm3_per_kpa : float
        Compliance C of what takes liquid outside the sensed sheet (the cell's
        margins and walls), mm^3 per kPa of liquid pressure near rest; 0 for a
        rigid cell.
    reservoir_capacity_mm3 : float
        The most the reservoir takes, V (``math.inf``: it never fills).
    seating_mm : float
        How far a rigid contact sinks into the membrane's surface (the rubber's
        waviness, a film of air under it) before it moves any liquid: what the
        thesis's Vernier read at its first weight beyond the membrane's own
        sink, which EIT does not see.
    seating_kpa : float
        Pressure scale of the seating: it closes as 1 - exp(-p / seating_kpa)
        (not fitted: every first weight of the tables, 0.78 kPa or more, has
        closed it).
    """

    rest_depth_mm: float = 6.378
    conductivity_s_per_m: float = 1.25
    temperature_coefficient_per_c: float = 0.02
    tension_n_per_m: float = 134.8
    foundation_kpa_per_mm: float = 0.0105
    slack_mm: float = 0.0
    contact_mm: float = 0.5
    hysteresis: float = 0.001647
    max_pressure_kpa: float = 50.0
    reservoir_mm3_per_kpa: float = 4208.0
    seating_mm: float = 0.3248
    seating_kpa: float = 0.1
    reservoir_capacity_mm3: float = 1335.0

    def __post_init__(self):
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if not np.isfinite(value) and not (field.name == "reservoir_capacity_mm3" and value == np.inf):
                raise ModelInputInvalid(f"mat parameter {field.name} must be finite, got {value!r}")
        for name in ("rest_depth_mm", "conductivity_s_per_m", "tension_n_per_m", "foundation_kpa_per_mm",
                     "contact_mm", "max_pressure_kpa", "seating_kpa", "reservoir_capacity_mm3"):
            if getattr(self, name) <= 0:
                raise ModelInputInvalid(f"mat parameter {name} must be positive, got {getattr(self, name)!r}")
        for name in ("temperature_coefficient_per_c", "slack_mm", "reservoir_mm3_per_kpa", "seating_mm"):
            if getattr(self, name) < 0:
                raise ModelInputInvalid(f"mat parameter {name} must not be negative, got {getattr(self, name)!r}")
        if not 0 <= self.hysteresis < 1:
            raise ModelInputInvalid(f"mat parameter hysteresis must be in [0, 1), got {self.hysteresis!r}")
        if self.contact_mm >= self.rest_depth_mm:
            raise ModelInputInvalid(f"contact_mm ({self.contact_mm}) must be below rest_depth_mm "
                                    f"({self.rest_depth_mm})")

    def description(self) -> dict:
        """The parameters by name, without those of a reservoir or a seating the mat does not have (their
        switch, ``reservoir_mm3_per_kpa`` or ``seating_mm``, at 0): what the mat's behaviour follows from,
        the same as before the mat model had them for a mat that has neither."""
        off = set()
        if self.reservoir_mm3_per_kpa == 0:
            off |= {"reservoir_mm3_per_kpa", "reservoir_capacity_mm3"}
        if self.seating_mm == 0:
            off |= {"seating_mm", "seating_kpa"}
        return {name: value for name, value in dataclasses.asdict(self).items() if name not in off}

    def conductivity_at(self, temperature_c: float) -> float:
        """Liquid conductivity at ``temperature_c``, S/m."""
        low, high = TEMPERATURE_RANGE_C
        if not (np.isfinite(temperature_c) and low <= temperature_c <= high):
            raise ModelInputInvalid(f"mat temperature {float(temperature_c)!r} C is outside the model's range "
                                    f"{low:g} to {high:g} C")
        return self.conductivity_s_per_m * (1.0 + self.temperature_coefficient_per_c * (temperature_c - 20.0))


# The defaults above are fitted by benchmarks/sensor_model.py to the 4, 9 and 25 cm2 tables of thesis
# chapter 6, both directions, with the thesis's front end and the liquid's warming of
# appliance/sim/load_test.py: rest depth, tension, reservoir and its capacity, seating and play by least
# squares on every row, each residual in units of its tolerance (25 % of the table for Q, dV/V and
# deformation, the sd for the rows back at zero pressure), then again with the misses beyond 20 % weighted
# up; the liquid's weight, the contact barrier, the seating's pressure scale, conductivity and its
# coefficient are not fitted. Residuals row by row, and the fit checked on each table left out of it, in
# benchmarks/sensor_model.md.
DEFAULT_PARAMETERS = MatParameters()

@dataclass(frozen=True)
class MatState:
    """What the mat remembers between two fields: the play's effective pressure (kPa, per cell), and
    the last deflection (mm) and liquid pressure (kPa), which only speed up the next solve."""

    effective_pressure_kpa: np.ndarray
    deflection_mm: np.ndarray
    liquid_pressure_kpa: float = 0.0


def sheet_conductance(params: MatParameters, field: PressureField, state: MatState | None = None,
                      temperature_c: float = 20.0, *, platen: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray, MatState]:
    """The mat's response to ``field``: sheet conductance, deflection and the state to pass next time.

    Parameters
    ----------
    params : MatParameters
    field : PressureField
        Pressure over the whole mat; its grid is the mechanics' grid, clamped at its edge.
    state : MatState, optional
        From the previous call on the same grid; None for a mat that has never been loaded.
    temperature_c : float
        Liquid temperature.
    platen : ndarray of bool, shape (rows, cols), optional
        Cells under a rigid flat platen (the thesis's weights): they move as one
        plane and share the load on them. None for a soft load such as a body.

    Returns
    -------
    conductance_s : ndarray, shape (rows, cols)
        Conductivity x liquid depth of each cell, S.
    deflection_mm : ndarray, shape (rows, cols)
        Membrane deflection, positive down; the liquid depth is ``rest_depth_mm - deflection_mm``.
    state : MatState

    Raises
    ------
    ModelInputInvalid
        A pressure above ``params.max_pressure_kpa``, a temperature outside the model's
        range, a state or platen for a grid of another shape.
    SolverError
        Newton's method did not converge.
    """
    state = _checked(params, field, state, platen)
    sigma = params.conductivity_at(temperature_c)
    p = field.pressure_kpa
    band = params.hysteresis * p
    effective = np.clip(state.effective_pressure_kpa, p - band, p + band)
    deflection, liquid = solve_deflection(params, effective, field.pitch_mm, platen, state.deflection_mm)
    conductance = sigma * (params.rest_depth_mm - deflection) * 1e-3
    return conductance, deflection, MatState(effective, deflection, liquid)


def _checked(params: MatParameters, field, state: MatState | None, platen) -> MatState:
    """Refuse a field the model is not valid for, or a state or platen of another grid; the state to use."""
    if not isinstance(field, PressureField):
        raise ModelInputInvalid(f"the mat needs a PressureField, got {type(field).__name__}")
    p = field.pressure_kpa
    if field.peak_kpa > params.max_pressure_kpa:
        i, j = np.unravel_index(np.argmax(p), p.shape)
        raise ModelInputInvalid(f"pressure {field.peak_kpa:.4g} kPa (row {i}, column {j}) is beyond the mat "
                                f"model's validity limit of {params.max_pressure_kpa:g} kPa")
    if state is not None and state.effective_pressure_kpa.shape != p.shape:
        raise ModelInputInvalid(f"mat state is for a {state.effective_pressure_kpa.shape} grid, the field is "
                                f"{p.shape}")
    if platen is not None and (np.shape(platen) != p.shape or np.asarray(platen).dtype != bool):
        raise ModelInputInvalid(f"a platen must be a boolean mask of the field's shape {p.shape}, got "
                                f"{np.asarray(platen).dtype} {np.shape(platen)}")
    return state if state is not None else MatState(np.zeros_like(p), np.zeros_like(p))


def reservoir_volume_mm3(params: MatParameters, liquid_pressure_kpa: float, slope: bool = False):
    """Liquid the reservoir outside the sensed sheet holds at ``liquid_pressure_kpa``, mm^3 (and, with
    ``slope``, its rate of change, mm^3 per kPa): C p at first, filling towards its capacity V as
    C p / (1 + C |p| / V)."""
    c, v = params.reservoir_mm3_per_kpa, params.reservoir_capacity_mm3
    give = 1.0 + c * abs(liquid_pressure_kpa) / v
    volume, rate = c * liquid_pressure_kpa / give, c / give**2
    return (volume, rate) if slope else volume


def surface_sink_mm(params: MatParameters, pressure_kpa):
    """How far a rigid contact pressing with ``pressure_kpa`` sinks into the membrane's surface, mm.

    Added to the membrane's deflection it is what a gauge on the contact reads;
    it moves no liquid, so the sheet conductance does not see it.
    """
    p = np.asarray(pressure_kpa, dtype=float)
    return params.seating_mm * -np.expm1(-np.maximum(p, 0.0) / params.seating_kpa)


def membrane_operator(shape: tuple[int, int], pitch_mm: float) -> sp.csr_matrix:
    """-lap on a cell-centred grid clamped at its outer edge (half a cell beyond the outer centres), 1/mm^2.

    Symmetric positive definite: the second difference of an edge cell sees the
    clamp through a mirror ghost cell (w_ghost = -w), so w is zero on the edge itself.
    """
    def second_difference(n):
        main = np.full(n, 2.0)
        main[[0, -1]] += 1.0
        return sp.diags([main, -np.ones(n - 1), -np.ones(n - 1)], [0, -1, 1]) if n > 1 else sp.diags([[4.0]], [0])

    rows, cols = shape
    return sp.csr_matrix((sp.kron(sp.identity(rows), second_difference(cols))
                          + sp.kron(second_difference(rows), sp.identity(cols))) / pitch_mm**2)


def foundation_force(params: MatParameters, deflection_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The foundation's pressure f(w) (kPa) and its slope df/dw (kPa/mm): slack, linear bed, contact barrier."""
    k, s, c, d0 = params.foundation_kpa_per_mm, params.slack_mm, params.contact_mm, params.rest_depth_mm
    w = deflection_mm
    if s > 0:
        t = np.tanh(w / s)
        force, slope = k * (w - s * t), k * t**2
    else:
        force, slope = k * w, np.full_like(w, k)
    down = np.maximum(w, 0.0)
    gap = d0 - down
    force = force + k * c**2 * (1.0 / gap - 1.0 / d0 - down / d0**2)
    slope = slope + np.where(w > 0, k * c**2 * (1.0 / gap**2 - 1.0 / d0**2), 0.0)
    return force, slope


def platen_basis(shape: tuple[int, int], platen: np.ndarray | None) -> sp.csr_matrix:
    """Map from the unknowns to every cell's deflection, shape (cells, unknowns).

    A free cell is its own unknown. The cells under a rigid flat platen share three:
    the platen's sink and its tilts about x and y (a tilt dropped when the platen is
    one cell wide that way), so the platen takes its load's force and moments whole.
    """
    n = shape[0] * shape[1]
    if platen is None or not platen.any():
        return sp.identity(n, format="csr")
    under = platen.ravel()
    free = np.flatnonzero(~under)
    cells = np.flatnonzero(under)
    i, j = np.unravel_index(cells, shape)
    columns = [np.ones(cells.size)]
    for coordinate in (j, i):
        centred = coordinate - coordinate.mean()
        if np.ptp(centred) > 0:
            columns.append(centred / np.abs(centred).max())
    rows = np.concatenate([free, np.repeat(cells, len(columns))])
    cols = np.concatenate([np.arange(free.size),
                           free.size + np.tile(np.arange(len(columns)), cells.size)])
    values = np.concatenate([np.ones(free.size), np.column_stack(columns).ravel()])
    return sp.csr_matrix((values, (rows, cols)), shape=(n, free.size + len(columns)))


def solve_deflection(params: MatParameters, pressure_kpa: np.ndarray, pitch_mm: float,
                     platen: np.ndarray | None = None, start_mm: np.ndarray | None = None,
                     max_steps: int = 100, solver: str = "multigrid") -> tuple[np.ndarray, float]:
    """Deflection (mm, positive down) and liquid pressure rise (kPa) under ``pressure_kpa`` (rows, cols).

    Damped Newton on -T lap(w) + f(w) + p_liquid = p with pitch^2 sum(w) equal to
    the reservoir's C p_liquid, over the unknowns of :func:`platen_basis`; a step
    never takes more than 90 % of the remaining gap to the base, so the depth
    stays positive. ``start_mm`` (the last
    deflection) is where Newton starts; it changes the steps taken, not the answer.
    ``solver`` solves each step's systems: ``"multigrid"`` by conjugate gradients on the grid's
    multigrid hierarchy, as loosely as Newton's progress allows (:mod:`appliance.sim.multigrid`: no
    factorisation of the mat), ``"direct"`` by a sparse factorisation per step, the reference it is
    checked against. Both stop on the same rule.
    """
    if solver not in SOLVERS:
        raise ModelInputInvalid(f"mechanics solver must be one of {', '.join(SOLVERS)}, got {solver!r}")
    shape = np.shape(pressure_kpa)
    p = np.asarray(pressure_kpa, dtype=float).ravel()
    if not p.any():
        return np.zeros(shape), 0.0
    mask = None if platen is None or not np.any(platen) else np.asarray(platen, dtype=bool)
    system = _bordered_system(shape, float(pitch_mm), params.tension_n_per_m,
                              None if mask is None else mask.tobytes())
    basis, stiffness, volume = system.basis, system.stiffness, system.volume
    load = system.basis_t @ p
    d0 = params.rest_depth_mm
    u = np.zeros(volume.size)
    if start_mm is not None:
        # Keep the warm start wherever it is a depth: a converged state's gap to the base is at least
        # about k c^2 / p_max (the barrier alone would carry the highest pressure there), so the ceiling,
        # half that gap above the base, never moves a state this model produced. (It used to be d0 / 2,
        # which restarted every cell deeper than that and left Newton crawling back 90 % of a gap at a time.)
        ceiling = d0 - 0.5 * params.foundation_kpa_per_mm * params.contact_mm**2 / params.max_pressure_kpa
        start = np.clip(np.ravel(start_mm), -d0, ceiling)
        u = system.projector.solve(system.basis_t @ start)
        deepest = float((basis @ u).max())
        if not np.isfinite(deepest):
            u = np.zeros(volume.size)
        elif deepest > ceiling:             # a platen's plane fitted to cells of another shape: shrink it back
            u *= ceiling / deepest
    w, liquid, held = basis @ u, 0.0, 0.0          # held: the reservoir's volume, mm^3
    cell_mm2 = float(pitch_mm) ** 2
    capacity = params.reservoir_capacity_mm3
    steps = InexactSteps(system.hierarchy) if solver == "multigrid" else _DirectSteps()
    for _ in range(max_steps):
        force, slope = foundation_force(params, w)
        residual = stiffness @ u + system.basis_t @ force + liquid * volume - load
        # Symmetric positive definite: the membrane's stiffness plus a non-negative diagonal.
        matrix = sp.csr_matrix(stiffness + system.basis_t @ sp.diags(slope) @ basis)
        x1, x2 = steps.solve(matrix, -residual, volume)
        # The bordered rows, linearised: pitch^2 sum(w) = held, and the reservoir's pressure at what it
        # holds is the liquid's (Schur complement on the liquid's pressure). The reservoir's volume is an
        # unknown beside the deflection: its pressure rises without bound as it fills, where a Newton
        # step on the liquid's pressure would overshoot into the flat of its filling volume.
        if params.reservoir_mm3_per_kpa > 0:
            pressure, stiffness_r = _reservoir_pressure(params, held)
            mismatch = pressure - liquid
            give = 1.0 / (cell_mm2 * stiffness_r)
            liquid_step = ((dot(volume, x1) + dot(volume, u) - held / cell_mm2 + mismatch * give)
                           / (dot(volume, x2) + give))
            held_step = (liquid_step - mismatch) / stiffness_r
        else:
            liquid_step, held_step = (dot(volume, x1) + dot(volume, u)) / dot(volume, x2), 0.0
        step = x1 - liquid_step * x2
        w_step = basis @ step
        deeper = w_step > 0
        t = min(1.0, 0.9 * float(np.min((d0 - w[deeper]) / w_step[deeper]))) if deeper.any() else 1.0
        if held_step and math.isfinite(capacity) and abs(held + held_step) >= capacity:
            t = min(t, 0.9 * (capacity - abs(held)) / abs(held_step))
        u, liquid, held = u + t * step, liquid + t * liquid_step, held + t * held_step
        w = basis @ u
        if t == 1.0 and np.abs(w_step).max() <= 1e-11 * d0 and abs(held_step) <= 1e-11 * d0 * cell_mm2:
            return w.reshape(shape), float(liquid)
    raise SolverError(f"mat mechanics did not converge in {max_steps} Newton steps (peak pressure "
                      f"{p.max():.4g} kPa, last step {np.abs(w_step).max():.3g} mm)")


class _DirectSteps:
    """A Newton step's systems by one sparse factorisation of its matrix."""

    def solve(self, matrix: sp.csr_matrix, rhs: np.ndarray, volume: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # Numbered in a fill-reducing order once for the grid: no ordering and no pivoting left to do.
        lu = spla.splu(sp.csc_matrix(matrix), permc_spec="NATURAL", diag_pivot_thresh=0.0,
                       options={"SymmetricMode": True})
        return lu.solve(rhs), lu.solve(volume)


def _reservoir_pressure(params: MatParameters, held_mm3: float) -> tuple[float, float]:
    """The inverse of :func:`reservoir_volume_mm3`: the pressure (kPa) at which the reservoir holds
    ``held_mm3``, and its rate of change (kPa per mm^3)."""
    c, v = params.reservoir_mm3_per_kpa, params.reservoir_capacity_mm3
    room = 1.0 - abs(held_mm3) / v
    return held_mm3 / (c * room), 1.0 / (c * room * room)


@dataclass(frozen=True)
class _BorderedSystem:
    """What a grid and platen fix for every solve: the basis (its unknowns numbered in a fill-reducing
    order), its transpose, the membrane's stiffness and each unknown's volume on them, and the
    factorised basis.T @ basis that projects a deflection onto the unknowns."""

    basis: sp.csr_matrix
    basis_t: sp.csr_matrix
    stiffness: sp.csr_matrix
    volume: np.ndarray
    projector: spla.SuperLU

    @functools.cached_property
    def hierarchy(self) -> MembraneHierarchy:
        """The multigrid hierarchy of the membrane's stiffness, made on the first solve that needs it."""
        return MembraneHierarchy(self.stiffness)


@functools.lru_cache(maxsize=8)
def _bordered_system(shape: tuple[int, int], pitch_mm: float, tension_n_per_m: float,
                     platen_bytes: bytes | None) -> _BorderedSystem:
    platen = None if platen_bytes is None else np.frombuffer(platen_bytes, dtype=bool).reshape(shape)
    basis = platen_basis(shape, platen)
    membrane = tension_n_per_m * membrane_operator(shape, pitch_mm)
    gram = sp.csr_matrix(basis.T @ basis)
    # The Newton matrix is stiffness + basis.T @ diag(slope) @ basis, whose pattern is that of
    # stiffness + gram: order its unknowns once by minimum degree on that pattern.
    pattern = sp.csc_matrix(basis.T @ membrane @ basis + gram)
    order = np.argsort(spla.splu(pattern, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                 options={"SymmetricMode": True}).perm_c)
    basis = sp.csr_matrix(basis[:, order])
    basis_t = sp.csr_matrix(basis.T)
    stiffness = sp.csr_matrix(basis_t @ membrane @ basis)
    volume = np.asarray(basis.sum(axis=0)).ravel()
    projector = spla.splu(sp.csc_matrix(basis_t @ basis))
    for matrix in (basis, basis_t, stiffness):
        for array in (matrix.data, matrix.indices, matrix.indptr):
            array.flags.writeable = False
    volume.flags.writeable = False
    return _BorderedSystem(basis, basis_t, stiffness, volume, projector)


def conductance_on_model(model: ForwardModel, conductance_grid: np.ndarray, pitch_mm: float) -> np.ndarray:
    """Per-element sheet conductance (S) of ``model``, sampled from a grid of cells of side ``pitch_mm``.

    Bilinear interpolation between cell centres at each element's centroid (the
    edge cells' values hold out to the mat's edge). Elements are about as large
    as the cells (2 mm against 2.3 mm for grid-4x4 at density 1), so the centroid
    value stands for the element. Elements the model fixes (metal electrodes of
    the network model) get the sampled value too; the model ignores it.

    Raises
    ------
    ModelInputInvalid
        The grid is not 2-D and positive, or the model reaches beyond it.
    """
    g = np.asarray(conductance_grid, dtype=float)
    if g.ndim != 2 or not np.isfinite(g).all() or (g <= 0).any():
        raise ModelInputInvalid("a conductance grid must be a 2-D array of positive finite values")
    rows, cols = g.shape
    xs, ys = (np.arange(cols) + 0.5) * pitch_mm, (np.arange(rows) + 0.5) * pitch_mm
    points = np.asarray(model.centroids_mm, dtype=float)
    reach = 1e-9 * max(cols, rows) * pitch_mm
    if (points.min(axis=0) < -reach).any() or points[:, 0].max() > cols * pitch_mm + reach \
            or points[:, 1].max() > rows * pitch_mm + reach:
        raise ModelInputInvalid(f"the model reaches beyond the {cols * pitch_mm:g} x {rows * pitch_mm:g} mm "
                                f"conductance grid")
    x = np.clip(points[:, 0], xs[0], xs[-1])
    y = np.clip(points[:, 1], ys[0], ys[-1])
    if rows == 1 or cols == 1:
        return np.full(len(points), float(g.mean()))
    return RegularGridInterpolator((ys, xs), g)(np.column_stack([y, x]))
