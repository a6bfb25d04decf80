"""Frame times that never go backwards, and the wall clock's steps noticed.

A board's frames are stamped in wall-clock seconds, for the records and the
screen. Taken straight from ``time.time()``, a step back (NTP correcting a
clock that ran ahead, a person setting the date) would give a frame an earlier
time than the last, which the alarm engine refuses. So frame times are the
wall clock read once, at start, advanced by the monotonic clock; each frame
compares the two, and a step of more than ``STEP_S`` is reported once for the
daemon to log. The steady time is not moved to follow a step: intervals (dose,
turn clock, escalation) stay true, at the cost of records offset from the new
wall clock until the next start.
"""

from __future__ import annotations

import time
from collections.abc import Callable

STEP_S = 5.0


class FrameClock:
    """Wall-clock seconds advanced by the monotonic clock; ``wall`` and ``monotonic`` are injectable."""

    def __init__(self, *, wall: Callable[[], float] = time.time, monotonic: Callable[[], float] = time.monotonic,
                 step_s: float = STEP_S):
        self._wall, self._monotonic, self.step_s = wall, monotonic, step_s
        self._origin = wall() - monotonic()
        self._offset = 0.0                  # the wall clock's lead over this clock at the last check

    def now(self) -> float:
        return self._origin + self._monotonic()

    def not_before(self, time_s: float) -> None:
        """Carry on after ``time_s`` (the last time recorded before a restart) even if the wall clock is now
        behind it, so a restart never takes the records back in time."""
        if self.now() <= time_s:
            self._origin += time_s - self.now() + 1e-3
            self._offset = self._wall() - self.now()

    def step(self) -> float | None:
        """The wall clock's step since the last call (seconds, negative for back), if more than ``step_s``."""
        offset = self._wall() - self.now()
        moved = offset - self._offset
        if abs(moved) <= self.step_s:
            return None
        self._offset = offset
        return moved
