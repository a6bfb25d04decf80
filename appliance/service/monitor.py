"""The monitor's main loop: each frame against the empty-mat reference, to a pressure map.

It holds the pieces fixed at start-up (the reconstruction model, the pressure
calibration, the reference frame) and refuses a calibration that does not fit
the model's layout and reconstruction, so a running appliance never reads
pressure through another mat's calibration. A frame that cannot be taken (a
bus or scan fault) is reported and the loop goes on with the next one.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from appliance.core.iterative import affordable_iterate
from appliance.core.model_cache import ReconstructionModel
from appliance.core.pressure import PressureCalibration, temperature_corrected
from appliance.core.pressure_map import PressureMap, pressure_map
from appliance.errors import ApplianceError, ConfigError


@dataclass(frozen=True)
class Fault:
    """A frame that could not be taken or imaged, and why."""

    time_s: float
    message: str
    consecutive: int


class Monitor:
    """Pressure maps from ``acquire()`` frames (``.volts``, ``.temperature_c``, ``.time_s``).

    ``iterate`` defaults to the calibration's own setting: a curve fitted to
    iterated images does not hold for one-step images, nor the other way round.
    """

    def __init__(self, acquire: Callable, model: ReconstructionModel, calibration: PressureCalibration, *,
                 iterate: str | None = None):
        setup = model.setup
        calibration.check_fits(setup.layout, setup.options.algorithm, model.reconstructor.grid.shape)
        self.acquire, self.model, self.calibration = acquire, model, calibration
        self.iterate = iterate or calibration.notes.get("iterate") or affordable_iterate(setup.layout.n_electrodes)
        self.reference: np.ndarray | None = None
        self.reference_temperature_c: float | None = None
        self.conditions: tuple = ()         # the technical conditions of the last frame acquired

    def take_reference(self, frame=None) -> None:
        """The empty mat (``frame``, or the next one acquired): every map is a change from it."""
        frame = frame if frame is not None else self.acquire()
        if not np.isfinite(frame.volts).any():
            raise ConfigError("the reference frame has no usable reading")
        self.reference = np.asarray(frame.volts, dtype=float)
        self.reference_temperature_c = frame.temperature_c

    def next_map(self) -> PressureMap:
        """Acquire one frame and turn it into a pressure map."""
        if self.reference is None:
            raise ConfigError("the monitor has no reference frame yet (take_reference first)")
        frame = self.acquire()
        self.conditions = tuple(getattr(frame, "conditions", ()))
        volts = frame.volts
        if self.reference_temperature_c is not None:
            volts = temperature_corrected(volts, frame.temperature_c, self.reference_temperature_c)
        image, info = self.model.reconstruct(volts, self.reference, iterate=self.iterate)
        return pressure_map(image, self.calibration, self.model.reconstructor.grid,
                            time_s=getattr(frame, "time_s", time.monotonic()), temperature_c=frame.temperature_c,
                            usable_readings=info["usable_readings"])

    def run(self, on_map: Callable[[PressureMap], None], *, frames: int | None = None,
            on_fault: Callable[[Fault], None] | None = None, pace: Callable[[], None] | None = None,
            should_stop: Callable[[], bool] = lambda: False) -> int:
        """Maps to ``on_map`` until ``frames`` were made or ``should_stop()``; faults go to ``on_fault``.

        ``pace()`` is called before each frame (to keep a frame rate). Returns the
        number of maps made.
        """
        made = consecutive = 0
        while (frames is None or made < frames) and not should_stop():
            if pace is not None:
                pace()
            try:
                result = self.next_map()
            except (ApplianceError, OSError) as exc:
                consecutive += 1
                if on_fault is not None:
                    on_fault(Fault(time.monotonic(), f"{type(exc).__name__}: {exc}", consecutive))
                continue
            consecutive = 0
            made += 1
            on_map(result)
        return made
