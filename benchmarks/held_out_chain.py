"""The held-out maps as the benchmarks read them: the true frame of a PmatData recording, and the default bed reading
it through the whole chain (virtual bed, parallel board, reconstruction, calibration) as ``appliance run`` does.
Shared by benchmarks/alerts.py, site_labels.py, training_nights.py and posture_choices.py."""

from __future__ import annotations

import appliance  # noqa: F401  (first: it pins BLAS to one thread before numpy loads)

from functools import lru_cache
from pathlib import Path

import numpy as np

from appliance.alerts.anatomy import BodyView, body_view
from appliance.core.model_cache import cached_model, default_setup
from appliance.core.named_layouts import get_layout
from appliance.service.assemble import virtual_calibration_path
from appliance.service.config_sections import MonitorConfig
from appliance.service.monitor import Monitor
from appliance.service.virtual_bed import VirtualBedSource
from appliance.sim.body import BED_GRID
from appliance.sim.recordings import RecordedScene, pmat_scene
from appliance.sim.scenes import load_scene
from appliance.sim.true_maps import on_pixels

PMAT = Path(__file__).resolve().parents[2] / "shared" / "data" / "pmatdata"
LAYOUT = get_layout(MonitorConfig().layout)
MINUTE = 60.0
POSTURE_OF_FILE = {1: "supine", 2: "right-90", 3: "left-90", 4: "right-30", 5: "right-60", 6: "left-30",
                   7: "left-60", 8: "supine", 9: "supine", 10: "supine", 11: "supine", 12: "supine",
                   13: "fetal-right", 14: "fetal-left", 15: "inclined", 16: "inclined", 17: "inclined"}


@lru_cache(maxsize=None)
def true_frame(subject: int, posture_file: int, shift: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """The middle frame of a recording (the one the labels were given on), 10 mm, scene frame, kPa."""
    scene = pmat_scene(PMAT, subject, posture_file, BED_GRID, shift_mm=shift)
    return scene.frames[len(scene.frames) // 2].copy()      # not a view: the recording is let go


class Chain:
    """The default bed read through the whole chain, as ``appliance run`` builds it."""

    def __init__(self, cache: Path):
        self.model, _ = cached_model(default_setup(LAYOUT), cache)
        source = VirtualBedSource(LAYOUT, load_scene("supine-still"), self.model.setup.protocol)
        self.calibration, _ = source.calibration(self.model, virtual_calibration_path(cache, self.model))
        self.grid = self.model.reconstructor.grid

    def true_view(self, frame: np.ndarray) -> BodyView:
        """A true frame (:func:`true_frame`) averaged over the monitor's pixels, as the body view the alert layer
        sees."""
        return body_view(on_pixels(frame, BED_GRID.pitch_mm, self.grid), self.grid)

    def read_still(self, frame: np.ndarray) -> np.ndarray:
        """The monitor's map (kPa) of ``frame`` held still, settled: the second of two a minute apart (the first
        one's fine readings are where the previous posture lay)."""
        return list(self.maps(still_scene(frame, 5 * MINUTE), [0.0, MINUTE]))[-1].pressure_kpa

    def maps(self, scene, times_s, seed: int = 0):
        """The monitor's map at each of ``times_s`` (one frame interval apart) of ``scene``."""
        step = float(times_s[1] - times_s[0]) if len(times_s) > 1 else MINUTE
        source = VirtualBedSource(LAYOUT, scene, self.model.setup.protocol, seed=seed, frame_interval_s=step)
        monitor = Monitor(source.acquire, self.model, self.calibration)
        monitor.take_reference(source.empty_reference())
        for _ in times_s:
            yield monitor.next_map()


def still_scene(frame: np.ndarray, seconds: float) -> RecordedScene:
    return RecordedScene(frame[None], np.zeros(1), BED_GRID, {"source": "held frame"}, duration_s=seconds)
