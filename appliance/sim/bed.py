"""The virtual bed: a scene on a mat, as the sensor the emulated front end measures.

At any time it gives the transfer impedances of the mat under the scene's
pressure: scene -> pressure field -> mat mechanics (membrane, liquid, hysteresis,
temperature) -> sheet conductance on the forward model's elements -> one
factorisation whose electrode block gives the transfer impedances
(:mod:`appliance.sim.transfer`; ``solver="fields"`` solves one field per
electrode instead, as :func:`~appliance.core.forward.solve_electrodes` does).
Only what the scene needs is computed: nothing while the scene and the
temperature stay as they were (a still patient costs no solve at all), and a
full re-solve when they change. A low-rank or local update does not pay on a
patient's movements: the liquid's volume is conserved and the membrane is slack
near rest, so the conductance moves over most of the mat, and a rank-r update
costs at least r solves through the old factorisation (benchmarks/simulator.md
measures both, and the detail a bed needs).

A scene lies head to foot along its grid's y; a bed layout lies along x, so the
field is turned to the layout when their sides are swapped.

>>> from appliance.core.named_layouts import get_layout
>>> from appliance.sim.scenes import load_scene
>>> bed = VirtualBed(get_layout("grid-8x16"), load_scene("supine-still"), density=0.5)
>>> z0 = bed.transfer_ohm(600.0); z1 = bed.transfer_ohm(660.0)   # lying still: one solve serves both
>>> bed.solves, bed.reuses, z0.shape
(1, 1, (128, 128))
>>> sorted(bed.seconds)                                             # where the solve's time went
['mechanics', 'scene', 'transfer']
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable

import numpy as np

from appliance.core.fem import build_fem_model
from appliance.core.forward import solve_electrodes
from appliance.calibration import BED_MIN_LENGTH_MM
from appliance.core.layouts import Layout
from appliance.errors import ModelInputInvalid
from appliance.sim.field import PressureField
from appliance.sim.mechanics import MatParameters, MatState, conductance_on_model, sheet_conductance
from appliance.sim.scene_base import Scene
from appliance.sim.transfer import TransferSolver

SOLVERS = ("block", "fields")

BED_MAT_PARAMETERS = MatParameters(rest_depth_mm=6.951, conductivity_s_per_m=1.25, temperature_coefficient_per_c=0.02,
                                   tension_n_per_m=71.08, foundation_kpa_per_mm=10.0, slack_mm=1.806,
                                   contact_mm=0.05, hysteresis=0.004465, max_pressure_kpa=50.0,
                                   reservoir_mm3_per_kpa=0.0, reservoir_capacity_mm3=math.inf, seating_mm=0.0)
"""The bed mat: the liquid, membrane and slack of the thesis's sensor as first fitted to its load tests, on
a foundation about eight times stiffer (a denser foam under the liquid: the thesis's chapter 7, "tailoring
the response to the pressure range"). On that first fit's foundation a body's pelvis bottoms the liquid out
above about 7.5 kPa (56 mmHg), so no reconstruction can tell 60 mmHg from 250; on this one 40 kPa (300
mmHg, above the highest interface pressures PmatData records) still leaves a sixth of the depth, and
10 mmHg thins it by about 15 %. Its own values, so that refitting the thesis's sensor leaves the bed as
designed: a sealed sheet that keeps its volume (no reservoir) and no seating, the bed mat as it was
designed before the thesis's sensor needed them."""


SMALL_MAT_PARAMETERS = dataclasses.replace(BED_MAT_PARAMETERS, foundation_kpa_per_mm=1.183)
"""A monitoring mat of the thesis's size: the same liquid, membrane and slack on the first fit's foam
foundation, which carries the 2 to 20 kPa soft loads a small mat is calibrated and tested with. The thesis's
sensor as measured (``DEFAULT_PARAMETERS``: its liquid rests on its own weight alone) puts the membrane on
the base under soft loads of 12 to 20 kPa over 9 cm2 and more (the thesis stopped its 25 cm2 test at 3.9
kPa); the load test and its fit are of that one."""


def mat_parameters_for(layout: Layout) -> MatParameters:
    """The mat a layout stands for: the bed mat on a bed-size sheet, the small monitoring mat otherwise."""
    return BED_MAT_PARAMETERS if max(layout.sheet.size_mm) >= BED_MIN_LENGTH_MM else SMALL_MAT_PARAMETERS


class VirtualBed:
    """``scene`` on ``layout``'s mat; ``temperature_c`` is a constant or a function of time (s).

    ``density`` is the forward mesh's and ``mechanics_merge`` merges the scene's cells in
    blocks before the mechanics: the detail a bed needs (benchmarks/simulator.md). ``solver``
    is ``"block"`` (the transfer alone, from one factorisation) or ``"fields"`` (a field per
    electrode, the slower path it is checked against). ``solves`` and ``reuses`` count the
    frames that re-solved and those served from the last solve; ``seconds`` adds up the
    solves' time by stage.
    """

    def __init__(self, layout: Layout, scene: Scene, *, params: MatParameters | None = None,
                 density: float = 1.0, temperature_c: float | Callable[[float], float] = 24.0,
                 mechanics_merge: int = 1, solver: str = "block"):
        if solver not in SOLVERS:
            raise ModelInputInvalid(f"solver must be one of {', '.join(SOLVERS)}, got {solver!r}")
        self.layout, self.scene, self.params = layout, scene, params or mat_parameters_for(layout)
        self.mechanics_merge = mechanics_merge
        self.solver = solver
        self.density = density
        self.model = build_fem_model(layout, density=density)          # numbered in a fill-reducing order
        self._block = TransferSolver(self.model) if solver == "block" else None
        self.temperature = temperature_c if callable(temperature_c) else (lambda t: float(temperature_c))
        self._turn = _orientation(scene, layout)
        self.state: MatState | None = None
        self._last: tuple[float, float] | None = None       # scene time and temperature of the cached solve
        self._transfer: np.ndarray | None = None
        self.solves = 0
        self.reuses = 0
        self.seconds = {"scene": 0.0, "mechanics": 0.0, "transfer": 0.0}

    @property
    def n_electrodes(self) -> int:
        return self.layout.n_electrodes

    def set_scene(self, scene: Scene) -> None:
        """Put another scene on the mat (a calibration weight, the next patient); the mat keeps its memory."""
        self._turn = _orientation(scene, self.layout)
        self.scene = scene
        self._transfer = None

    def temperature_at(self, now_s: float) -> float:
        return self.temperature(now_s)

    def field_at(self, now_s: float) -> PressureField:
        """The scene's pressure at ``now_s`` in the layout's orientation (held after the scene ends)."""
        field = self.scene.pressure_at(min(max(now_s, 0.0), self.scene.duration_s))
        return PressureField(field.pressure_kpa.T, field.pitch_mm) if self._turn else field

    def transfer_ohm(self, now_s: float) -> np.ndarray:
        """Transfer impedances at ``now_s`` (ohm), re-solved only if the scene or temperature changed."""
        t = min(max(now_s, 0.0), self.scene.duration_s)
        temperature = self.temperature(now_s)
        if self._transfer is not None and self._last is not None and self._last[1] == temperature and \
                not self.scene.changes(min(self._last[0], t), max(self._last[0], t)):
            self.reuses += 1
            return self._transfer
        conductance, pitch_mm = self._mat_at(t, temperature)
        start = time.perf_counter()
        sigma = conductance_on_model(self.model, conductance, pitch_mm)
        if self._block is not None:
            self._transfer = self._block.transfer(sigma)
        else:
            self._transfer = solve_electrodes(self.model, sigma).transfer
        self.seconds["transfer"] += time.perf_counter() - start
        self._last = (t, temperature)
        self.solves += 1
        return self._transfer

    def remember(self, times_s) -> None:
        """Leave the mat's memory (its frictional play) where frames at ``times_s`` would have left it: a
        monitor restarting mid-scene finds the mat as it was, not freshly loaded. Only the times after the
        scene changed are solved, since the same load again leaves the memory as it is; no readings. The
        empty mat the scene starts from has none (its play closes at zero load)."""
        self.state, last = None, None
        for t in times_s:
            t = min(max(t, 0.0), self.scene.duration_s)
            if last is None or self.scene.changes(min(last, t), max(last, t)):
                self._mat_at(t, self.temperature(t))
            last = t
        self._transfer = None

    def _mat_at(self, t: float, temperature: float) -> tuple[np.ndarray, float]:
        """The sheet's conductance under the scene at ``t`` on the mechanics' grid, and its pitch (mm); the
        mat's memory moves on."""
        start = time.perf_counter()
        field = self.field_at(t)
        platen = getattr(self.scene, "platen", None)
        if platen is not None and self._turn:
            platen = platen.T
        if self.mechanics_merge > 1:
            field = field.coarsened(self.mechanics_merge)
            platen = None if platen is None else _merged_mask(platen, self.mechanics_merge)
        scene_done = time.perf_counter()
        conductance, _, self.state = sheet_conductance(self.params, field, self.state, temperature, platen=platen)
        self.seconds["scene"] += scene_done - start
        self.seconds["mechanics"] += time.perf_counter() - scene_done
        return conductance, field.pitch_mm


def _merged_mask(mask: np.ndarray, factor: int) -> np.ndarray:
    rows, cols = mask.shape
    return mask.reshape(rows // factor, factor, cols // factor, factor).mean(axis=(1, 3)) >= 0.5


def _orientation(scene: Scene, layout: Layout) -> bool:
    """Whether the scene's field must be transposed to lie on the layout's sheet."""
    width, height = layout.sheet.size_mm
    grid = scene.grid
    pitch = grid.pitch_mm
    if abs(grid.width_mm - width) <= pitch and abs(grid.height_mm - height) <= pitch:
        return False
    if abs(grid.width_mm - height) <= pitch and abs(grid.height_mm - width) <= pitch:
        return True
    raise ModelInputInvalid(f"the scene's {grid.width_mm:g} x {grid.height_mm:g} mm mat does not fit layout "
                            f"{layout.name!r} ({width:g} x {height:g} mm)")
