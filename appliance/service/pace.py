"""Keeping a frame rate in wall time, so a stop request ends the wait at once."""

from __future__ import annotations

import threading
import time


class Pace:
    """Frames every ``period_s`` of wall time (0: no waiting); a late frame is not made up for."""

    def __init__(self, period_s: float):
        self.period_s = period_s
        self._next: float | None = None

    def wait(self, stop: threading.Event) -> bool:
        """Wait for the next frame's turn; False if ``stop`` was set meanwhile."""
        now = time.monotonic()
        if self._next is not None and self._next > now and stop.wait(self._next - now):
            return False
        self._next = max(now, self._next or now) + self.period_s
        return True
