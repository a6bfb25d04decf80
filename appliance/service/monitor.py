"""The monitor's main loop: each frame against the empty-mat reference, to a pressure map.

It holds the pieces fixed at start-up (the reconstruction model, the pressure
calibration, the reference frame) and refuses a calibration that does not fit
the model's layout and reconstruction, so a running appliance never reads
pressure through another mat's calibration. The loop around it, and what a
frame that cannot be taken becomes, is the daemon's (:mod:`appliance.service.daemon`).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from appliance.core.iterative import affordable_iterate
from appliance.core.model_cache import ReconstructionModel, return_freed_memory
from appliance.core.pressure import PressureCalibration, temperature_corrected
from appliance.core.pressure_map import PressureMap, loaded_electrodes, pressure_map
from appliance.drivers.scan import SATURATION_PART, Flag, TechnicalCondition
from appliance.errors import ConfigError


SATURATION_ALARM_SHARE = 0.05
"""Saturated readings are left out of the image; only when more than this share of a frame is lost
to them (a short, a failing gain stage, a load far beyond the mat's range) does the image suffer enough
for a technical alarm. A lateral tilt on the bed saturates up to 6 of 6020 readings (0.1 %)."""


RETURN_MEMORY_FRAMES = 60
"""Every this many maps the pages freed since go back to the system: each frame's work space is freed,
but glibc keeps what is not at the top of its heap, so a night of the bed's frames held more of it the
longer it ran. Sixty is an hour of the bed's frames at one a minute; a trim costs under a millisecond."""


CALIBRATION_MAX_AGE_DAYS = 365.0
"""A mat's foam and liquid age; a calibration older than a year is due again (a yearly service)."""
CALIBRATION_MAX_DELTA_C = 5.0
"""The temperature correction is first order, measured to hold within 0.5 % over +-3 C (benchmarks/pressure.md);
beyond 5 C from the calibration's temperature the map's pressures are not trusted."""


def stale_calibration(calibration: PressureCalibration, temperature_c: float | None,
                      now_s: float | None = None) -> TechnicalCondition | None:
    """``calibration`` as a technical condition when it is too old or the liquid too far from its temperature."""
    made = calibration.notes.get("made_at")
    age_days = ((time.time() if now_s is None else now_s) - made) / 86400.0 if made is not None else None
    if age_days is not None and age_days > CALIBRATION_MAX_AGE_DAYS:
        return TechnicalCondition("calibration", f"made {age_days:.0f} days ago: the mat is due for calibration")
    if temperature_c is not None and abs(temperature_c - calibration.reference_temperature_c) > CALIBRATION_MAX_DELTA_C:
        return TechnicalCondition("calibration", f"the liquid is at {temperature_c:.1f} C, calibrated at "
                                                 f"{calibration.reference_temperature_c:.1f} C: pressures are not "
                                                 "trusted")
    return None


def alarm_worthy(frame) -> tuple[TechnicalCondition, ...]:
    """The frame's technical conditions that stop or degrade monitoring: every one but a few saturated
    readings, which become ``saturation`` only above ``SATURATION_ALARM_SHARE``."""
    conditions = tuple(c for c in getattr(frame, "conditions", ()) if c.part != SATURATION_PART)
    flags = getattr(frame, "flags", None)
    if flags is None:
        return conditions
    saturated = int(np.count_nonzero(np.asarray(flags) & int(Flag.SATURATED)))
    if saturated > SATURATION_ALARM_SHARE * len(flags):
        conditions += (TechnicalCondition("saturation", f"{saturated} of {len(flags)} readings over range even at "
                                                        "the lowest gain: the map is degraded"),)
    return conditions


def reference_state(model, frame, fit) -> dict:
    """What the store keeps of an empty-mat reference: its readings and temperature, and the contact fit
    made to it (for an engineer; a restart fits the same readings again)."""
    return {"layout": model.setup.layout.name,
            "volts": [None if not np.isfinite(v) else float(v) for v in frame.volts],
            "temperature_c": frame.temperature_c, "contact_fit": None if fit is None else fit.summary()}


class Monitor:
    """Pressure maps from ``acquire()`` frames (``.volts``, ``.temperature_c``, ``.time_s``).

    ``iterate`` defaults to the calibration's own setting: a curve fitted to
    iterated images does not hold for one-step images, nor the other way round.
    With ``adaptive`` the front end reads finely only around the electrodes the last
    map found a body on: ``acquire(loaded=...)``, None for a full pass (the first frame,
    and after an empty map: the frame a patient lies down in is read whole, not from
    the empty mat's held fine readings, which made one frame of scattered false peaks).
    """

    def __init__(self, acquire: Callable, model: ReconstructionModel, calibration: PressureCalibration, *,
                 iterate: str | None = None, adaptive: bool = False):
        setup = model.setup
        calibration.check_fits(setup.layout, setup.options.algorithm, model.reconstructor.grid.shape)
        self.acquire, self.model, self.calibration = acquire, model, calibration
        self.adaptive = adaptive
        self.loaded: list[int] | None = None    # electrodes under the body in the last map (adaptive front ends)
        self.iterate = iterate or calibration.notes.get("iterate") or affordable_iterate(setup.layout.n_electrodes)
        self.reference: np.ndarray | None = None
        self.reference_temperature_c: float | None = None
        self.conditions: tuple = ()         # the alarm-worthy technical conditions of the last frame acquired
        self.maps_made = 0                  # to return freed memory every RETURN_MEMORY_FRAMES maps

    def take_reference(self, frame=None, progress=None):
        """The empty mat (``frame``, or the next one acquired): every map is a change from it.
        Returns the contact fit made to it, as :meth:`set_reference`."""
        frame = frame if frame is not None else self.acquire()
        if not np.isfinite(frame.volts).any():
            raise ConfigError("the reference frame has no usable reading")
        return self.set_reference(frame.volts, frame.temperature_c, progress)

    def set_reference(self, volts, temperature_c: float | None, progress=None):
        """Image every frame against ``volts``, the empty mat at ``temperature_c``.

        The model is fitted to the reference here (each electrode's contact and the
        sheet's conductance, then relinearised: ``ReconstructionModel.for_reference``)
        and its reconstructor factorised, so the cost falls now and not on the next frame.
        Returns the fit (None where the setup does not fit contacts).

        Raises
        ------
        ReconstructionError
            The readings do not fit the model (another mat, reversed leads); the reference
            is left as it was.
        """
        volts = np.asarray(volts, dtype=float)
        fitted = self.model.for_reference(volts, progress)
        fitted.for_readings(~np.isfinite(volts)).pixels(volts, volts)    # its factors made now, not at the first frame
        self.reference, self.reference_temperature_c = volts, temperature_c
        self.loaded = None                                   # a full pass first, as after any new reference
        return fitted.contact_fit

    def next_map(self) -> PressureMap:
        """Acquire one frame and turn it into a pressure map."""
        if self.reference is None:
            raise ConfigError("the monitor has no reference frame yet (take_reference first)")
        frame = self.acquire(loaded=self.loaded) if self.adaptive else self.acquire()
        stale = stale_calibration(self.calibration, frame.temperature_c)
        self.conditions = alarm_worthy(frame) + ((stale,) if stale is not None else ())
        volts = frame.volts
        if self.reference_temperature_c is not None:
            volts = temperature_corrected(volts, frame.temperature_c, self.reference_temperature_c)
        image, info = self.model.reconstruct(volts, self.reference, iterate=self.iterate)
        grid = self.model.reconstructor.grid
        result = pressure_map(image, self.calibration, grid, time_s=getattr(frame, "time_s", time.monotonic()),
                              temperature_c=frame.temperature_c, usable_readings=info["usable_readings"])
        if self.adaptive:
            self.loaded = loaded_electrodes(result.pressure_kpa, grid, self.model.setup.layout.centroids_mm()) or None
        self.maps_made += 1
        if self.maps_made % RETURN_MEMORY_FRAMES == 0:
            return_freed_memory()
        return result
