"""AD8251 programmable-gain instrumentation amplifier (gain 1, 2, 4, 8) in latched mode.

Three GPIOs drive it: A0 and A1 choose the gain, and the falling edge of /WR
latches them. Between latches A0/A1 may change freely (they can be shared with
other address lines). The driver sets A1/A0 with /WR high, then drops /WR in a
separate call, so the address lines are settled before the edge (setup time),
and raises /WR again afterwards. Changing A0/A1 in the same call as the /WR
edge would violate the setup time, and the emulator rejects it.
"""

from __future__ import annotations

from appliance.drivers.bus import GPIOLines, LineRequest


class AD8251:
    """One AD8251 with its A0, A1 and /WR lines, requested as outputs with /WR initially 1."""

    GAINS = (1, 2, 4, 8)
    """Gain by A1A0 code: 00, 01, 10, 11."""

    def __init__(self, gpio: GPIOLines, *, a0: str, a1: str, wr: str):
        missing = [name for name in (a0, a1, wr) if name not in gpio.names]
        if missing:
            raise ValueError(f"AD8251: GPIO line {missing[0]} was not requested (lines: {', '.join(gpio.names)})")
        self.gpio = gpio
        self.a0, self.a1, self.wr = a0, a1, wr
        self._gain: float = 1

    @staticmethod
    def line_request(a0: str, a1: str, wr: str) -> LineRequest:
        """The outputs the driver needs: A0 and A1 low, /WR high (no latch on request)."""
        return LineRequest(outputs={a0: 0, a1: 0, wr: 1}, inputs={})

    def set_gain(self, gain: float) -> None:
        """Latch ``gain``: A1/A0 with /WR high, then /WR low (the latching edge), then /WR high."""
        if gain not in self.GAINS:
            raise ValueError(f"AD8251 gain {gain!r} is not one of {self.GAINS}")
        code = self.GAINS.index(gain)
        self.gpio.set_values({self.a1: code >> 1, self.a0: code & 1, self.wr: 1})
        self.gpio.set_values({self.wr: 0})
        self.gpio.set_values({self.wr: 1})
        self._gain = gain

    @property
    def gain(self) -> float:
        """The gain last latched by this driver (1, the chip's power-up gain, before any)."""
        return self._gain
