"""Simulated time: waits advance a counter instead of sleeping.

Every emulated bus charges its transfers to the same clock, so the time a scan
takes under emulation is the frame time of the board's timing model, and a
driver that reads before a chip has settled gets the unsettled value.

>>> clock = SimulatedClock()
>>> clock.sleep(0.25); clock.monotonic()
0.25
"""

from __future__ import annotations

from appliance.drivers.bus import Clock


class SimulatedClock(Clock):
    """A clock that only moves when somebody waits or a bus transfer is charged to it."""

    def __init__(self, start_s: float = 0.0):
        self._now = float(start_s)

    def monotonic(self) -> float:
        return self._now

    def sleep(self, seconds: float) -> None:
        if seconds < 0:
            raise ValueError(f"cannot wait a negative time ({seconds!r} s)")
        self._now += seconds
