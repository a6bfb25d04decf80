"""The appliance's embedded default: the virtual bed as its front end, calibrated as a factory would.

With no hardware, the monitor measures a simulated patient (a scene) on a
simulated mat through the simulated analogue chain. Before the patient is put
on, the empty mat gives the reference frame and, the first time, a pressure
calibration: the same procedure with the same loads as on a real mat, kept in
the data directory under the layout's and reconstruction's name.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import threading
from collections.abc import Callable
from importlib import resources
from pathlib import Path

import numpy as np

from appliance.calibration import calibration_loads, pressure_calibration
from appliance.core.layouts import Layout
from appliance.core.model_cache import ReconstructionModel
from appliance.core.pressure import PressureCalibration, load_pressure_calibration, save_pressure_calibration
from appliance.errors import DataFileInvalid
from appliance.service.pace import Pace
from appliance.sim.bed import VirtualBed
from appliance.sim.frontend import VirtualFrontEnd
from appliance.sim.loads import placer
from appliance.sim.scene_base import Scene


class VirtualBedSource:
    """``scene`` on ``layout``'s simulated mat, read every ``frame_interval_s`` of scene time.

    As the monitor daemon's frame source it runs on scene time: a frame every
    ``frame_interval_s / speed`` wall seconds (``speed`` 0: no waiting), ending
    with the scene, and resuming after a restart at the frame after the last one
    the store holds.
    """

    def __init__(self, layout: Layout, scene: Scene, protocol, *, seed: int = 0, frame_interval_s: float = 1.0,
                 speed: float = 0.0, profile=None, **bed_options):
        self.scene = scene
        self.bed = VirtualBed(layout, scene, **bed_options)
        self.front_end = VirtualFrontEnd(self.bed, protocol, profile=profile, seed=seed,
                                         frame_interval_s=frame_interval_s)
        self.place = placer(self.bed)
        self.pace = Pace(frame_interval_s / speed if speed > 0 else 0.0)

    @property
    def adaptive(self) -> bool:
        return self.front_end.adaptive

    def acquire(self, loaded=None):
        return self.front_end.acquire(loaded)

    def now(self) -> float:
        """The scene time of the next frame."""
        return self.front_end.time_s

    def wait_for_frame(self, stop: threading.Event) -> bool:
        """Wait for the next frame's turn; False when the scene is over or ``stop`` was set meanwhile."""
        return self.front_end.time_s <= self.scene.duration_s and self.pace.wait(stop)

    def resume_after(self, time_s: float) -> None:
        """Carry on with the frame after scene time ``time_s`` (the last one recorded before a restart), on
        the mat as the frames up to it left it."""
        self.start_scene()
        interval = self.front_end.frame_interval_s
        self.bed.remember(np.arange(0.0, time_s + interval / 2, interval))
        self.front_end.time_s = time_s + interval

    def reference(self):
        """The empty-mat reference the daemon takes on a fresh start."""
        return self.empty_reference()

    def empty_reference(self):
        """A frame of the empty mat; the patient's scene then starts from its beginning."""
        self.place(None)
        frame = self.front_end.acquire()
        self.start_scene()
        return frame

    def start_scene(self) -> None:
        self.bed.set_scene(self.scene)
        self.front_end.time_s = 0.0
        self.front_end.schedule_faults(self.scene.faults)

    def mat_key(self) -> str:
        """SHA-256 of what the virtual mat's readings follow from: its mechanics, mesh and front end's analogue
        parts."""
        # The profile without its wiring (pins, buses, host boards): moving a chip select changes no reading.
        profile = dataclasses.replace(self.front_end.chain.profile, spi={}, i2c={}, i2c_bus=0, gpio={}, system="",
                                      boards=())
        description = {"mat": self.bed.params.description(), "density": self.bed.density,
                       "front_end": repr(profile), "current_a": self.front_end.chain.current_a}
        return hashlib.sha256(json.dumps(description, sort_keys=True, default=str).encode()).hexdigest()

    def fits(self, calibration: PressureCalibration, model: ReconstructionModel) -> bool:
        """Whether ``calibration`` was made on this virtual mat for ``model``'s reconstruction."""
        return calibration.notes.get("setup") == model.setup.image_key() and \
            calibration.notes.get("mat") == self.mat_key()

    def stamped(self, calibration: PressureCalibration, model: ReconstructionModel) -> PressureCalibration:
        """``calibration`` (made on this virtual mat) marked with what it fits, for :meth:`fits`."""
        return dataclasses.replace(calibration, notes={**calibration.notes, "setup": model.setup.image_key(),
                                                       "mat": self.mat_key()})

    def calibration(self, model: ReconstructionModel, path: Path, *,
                    progress: Callable | None = None) -> tuple[PressureCalibration, bool]:
        """The calibration the package ships for this virtual mat and ``model`` (:data:`SHIPPED_CALIBRATIONS`:
        made from people's pressure maps, which a bed mat needs and a fresh appliance does not have); else the
        one at ``path`` if it was made on this virtual mat for ``model``; else one made now from weights on the
        empty mat. The shipped one comes first, so a package that ships a new calibration is not overruled by
        the copy an earlier version left at ``path``. What is returned is saved at ``path``.

        Returns it and whether it was made now.
        """
        shipped = shipped_calibration(model.setup.layout.name)
        if shipped is not None and self.fits(shipped, model):
            calibration, made = shipped, False
        elif (own := self._fitting_file(path, model)) is not None:
            return own, False
        else:
            calibration, made = self.stamped(pressure_calibration(self.acquire, self.place, model,
                                                                  calibration_loads(model.setup.layout),
                                                                  progress=progress), model), True
            self.start_scene()
        path.parent.mkdir(parents=True, exist_ok=True)
        save_pressure_calibration(path, calibration)
        return calibration, made

    def _fitting_file(self, path: Path, model: ReconstructionModel) -> PressureCalibration | None:
        """The calibration in ``path`` if it is there, readable and made on this virtual mat for ``model``."""
        if not path.exists():
            return None
        try:
            calibration = load_pressure_calibration(path)
        except DataFileInvalid:
            return None                 # the virtual mat's own file, damaged: made again
        return calibration if self.fits(calibration, model) else None


SHIPPED_CALIBRATIONS = "calibrations"
"""The folder of ``appliance.sim`` holding the virtual mats' calibrations made from people's pressure maps
(``appliance calibrate pressure --maps``), one per layout, ``<layout>.json``; benchmarks/bed.md says how
each was made and how it reads people it was not made from."""


def shipped_calibration(layout_name: str) -> PressureCalibration | None:
    """The calibration the package ships for the virtual mat of ``layout_name``, or None."""
    path = resources.files("appliance.sim").joinpath(SHIPPED_CALIBRATIONS, f"{layout_name}.json")
    if not path.is_file():
        return None
    with resources.as_file(path) as file:
        return load_pressure_calibration(file)
