"""The front end board as the monitor daemon's frame source: the scan engine, on the wall clock.

``[board] backend = "linux"`` reads the real chips; ``"emulated"`` runs the
register-level emulators on a still, empty mat of the layout (for trying a
configuration without hardware). Frames are stamped with the wall clock, so
the dose and turn clock carry on across a restart by real elapsed time; while
running, the wall clock only sets the start and the monotonic clock moves it on
(:class:`~appliance.service.clock.FrameClock`), so a step of the wall clock
cannot stop the alarm engine.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from appliance.core.layouts import Layout
from appliance.drivers.scan import TechnicalCondition
from appliance.service.clock import FrameClock
from appliance.service.pace import Pace


@dataclass(frozen=True)
class BoardFrame:
    volts: np.ndarray
    flags: np.ndarray
    temperature_c: float | None
    time_s: float
    conditions: tuple[TechnicalCondition, ...]


class BoardSource:
    """A scan every ``frame_interval_s`` of wall time (or as fast as the scan goes, if that is slower)."""

    def __init__(self, board_table: dict, layout: Layout, protocol, *, frame_interval_s: float, seed: int = 0,
                 clock: FrameClock | None = None):
        from appliance.drivers.backend import open_board, open_front_end
        from appliance.drivers.emulated.sensor import ForwardSensor
        from appliance.drivers.scan import ScanEngine

        self.board, profile = open_board(board_table, sensor=lambda: ForwardSensor.of_layout(layout), seed=seed)
        self.front_end = open_front_end(self.board, profile)
        self.engine = ScanEngine(self.front_end, protocol)
        self.pace = Pace(frame_interval_s)
        self.clock = clock or FrameClock()

    @property
    def adaptive(self) -> bool:
        """Whether the board can read adaptively (a parallel front end built for a grid)."""
        return self.engine.adaptive is not None

    def acquire(self, loaded=None) -> BoardFrame:
        frame = self.engine.scan(loaded)
        return BoardFrame(frame.volts, frame.flags, frame.temperature_c, self.clock.now(), frame.conditions)

    def now(self) -> float:
        return self.clock.now()

    def clock_step(self) -> float | None:
        """The wall clock's step since the last frame, if larger than a few seconds (for the log)."""
        return self.clock.step()

    def wait_for_frame(self, stop: threading.Event) -> bool:
        return self.pace.wait(stop)

    def resume_after(self, time_s: float) -> None:
        """Carry on after the last time recorded: the wall clock went on while the monitor was down, unless it
        was set back, when the records still go forward."""
        self.clock.not_before(time_s)

    def reference(self) -> BoardFrame:
        """The next frame, taken as the empty mat's (the installer clears the mat before the first start)."""
        return self.acquire()

    def close(self) -> None:
        self.front_end.close()
        self.board.close()
