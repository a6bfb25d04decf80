"""AD7606 emulators: conversions on the shared CONVST in simulated time, serial read-out, BUSY, RESET, RANGE.

What they enforce and model (the facts are those of :mod:`appliance.drivers.ad7606`):

- A conversion before the first RESET pulse after power-up is an
  :class:`EmulatorViolation`: the data sheet leaves the part undefined until reset.
- A rising CONVST edge samples the eight inputs of every converter at that
  instant; with oversampling N the other N - 1 samples follow at equal steps
  over the conversion time and are averaged (the digital filter), so inputs that
  are still settling, or that change during a long conversion, show in the result.
- BUSY (the OR of all converters) is high for the conversion time of the
  strapped oversampling ratio; the output registers change when it falls, so a
  read before then returns the previous conversion (noted in ``warnings``).
- A CONVST edge while converting is ignored (noted); RANGE changing while a
  conversion runs, or in the same call as the CONVST edge (no setup time), is an
  :class:`EmulatorViolation`.
- Read-out: SPI modes 2 and 3 only (SCLK idles high: in modes 0 and 1 the first
  rising edge would shift the MSB out before it is sampled), whole 16-bit
  words; each frame continues from the channel the last one stopped at, and the
  pointer returns to V1 when a conversion starts and when it ends; words past V8
  read 0.
- Codes: 16-bit two's complement of the averaged input at the RANGE in force at
  the CONVST edge, with ``noise_lsb`` of converter noise, clipped to the
  extreme codes. ``stuck_code`` makes every channel return that code, as a
  converter whose digital side has locked up would.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from appliance.drivers.ad7606 import CHANNELS, CONVERSION_S, FULL_SCALES_V
from appliance.drivers.bus import FALLING
from appliance.drivers.emulated.buses import EmulatorViolation, GPIOBank, InputSource, SPIChipEmulator


class EmulatedAD7606(SPIChipEmulator):
    """One converter; ``inputs(t)`` gives its eight input voltages at time ``t``."""

    name = "AD7606"
    modes = frozenset({2, 3})
    max_speed_hz = 17_000_000

    def __init__(self, clock, inputs: Callable[[float], np.ndarray], *, oversampling: int = 1,
                 noise_lsb: float = 0.5, seed: int = 0):
        if oversampling not in CONVERSION_S:
            raise ValueError(f"AD7606 oversampling {oversampling!r} is not one of {tuple(CONVERSION_S)}")
        self.clock, self.inputs, self.oversampling, self.noise_lsb = clock, inputs, oversampling, noise_lsb
        self.rng = np.random.default_rng(seed)
        self.stuck_code: int | None = None
        self.warnings: list[str] = []
        self.conversions = 0
        self._power_on()

    def _power_on(self) -> None:
        self.was_reset = False
        self.registers = [0] * CHANNELS
        self.pointer = 0
        self.conversion: dict | None = None       # times, samples taken, end, full scale

    def reset(self) -> None:
        """Power cycle: registers cleared, and a RESET pulse needed again before converting."""
        self._power_on()

    def reset_pulse(self) -> None:
        """The RESET pin's pulse: a conversion in progress is abandoned, the part is ready."""
        self.conversion = None
        self.pointer = 0
        self.was_reset = True

    @property
    def conversion_s(self) -> float:
        return CONVERSION_S[self.oversampling]

    # -- conversions -------------------------------------------------------------------
    def start(self, now: float, full_scale_v: float) -> bool:
        """A CONVST rising edge at ``now``; False if the part ignored it (busy)."""
        if not self.was_reset:
            raise EmulatorViolation("AD7606: CONVST before any RESET pulse; the data sheet requires a reset after "
                                    "power-up before the first conversion")
        self._finish_if_done(now)
        if self.conversion is not None:
            self.warnings.append(f"CONVST at {now:.6f} s while converting: ignored")
            return False
        step = self.conversion_s / self.oversampling
        self.conversion = {"times": [now + i * step for i in range(self.oversampling)], "samples": [],
                           "end": now + self.conversion_s, "full_scale": full_scale_v}
        self.pointer = 0
        self.take_due(now)
        return True

    def take_due(self, now: float) -> None:
        """Sample the inputs at every sampling instant up to ``now`` (before the analogue state changes)."""
        c = self.conversion
        if c is None:
            return
        while len(c["samples"]) < len(c["times"]) and c["times"][len(c["samples"])] <= now:
            c["samples"].append(np.asarray(self.inputs(c["times"][len(c["samples"])]), dtype=float))

    def busy(self, now: float) -> bool:
        self._finish_if_done(now)
        return self.conversion is not None

    def _finish_if_done(self, now: float) -> None:
        c = self.conversion
        if c is None or now < c["end"]:
            return
        self.take_due(c["end"])
        lsb = c["full_scale"] / 32768
        mean = np.mean(c["samples"], axis=0) / lsb
        mean += self.noise_lsb / np.sqrt(self.oversampling) * self.rng.standard_normal(CHANNELS)
        codes = np.clip(np.round(mean), -32768, 32767).astype(int)
        if self.stuck_code is not None:
            codes[:] = self.stuck_code
        self.registers = [int(code) for code in codes]
        self.pointer = 0
        self.conversion = None
        self.conversions += 1

    # -- SPI -----------------------------------------------------------------------------
    def check_frame(self, data: bytes) -> None:
        if not data or len(data) % 2:
            raise EmulatorViolation(f"AD7606: a read of {len(data)} bytes is not a whole number of 16-bit words")

    def frame(self, data: bytes) -> bytes:
        now = self.clock.monotonic()
        self._finish_if_done(now)
        if self.conversion is not None:
            self.warnings.append(f"read at {now:.6f} s before BUSY fell: the previous conversion's result")
        out = bytearray()
        for _ in range(len(data) // 2):
            code = self.registers[self.pointer] if self.pointer < CHANNELS else 0
            self.pointer += 1
            out += int(code).to_bytes(2, "big", signed=True)
        return bytes(out)


class AD7606Pins(InputSource):
    """The control lines every converter shares: CONVST (tied A/B), RESET, RANGE in; BUSY (ORed) out.

    Watches the lines on ``bank`` and drives the converters; it is the input source of the BUSY line.
    """

    def __init__(self, bank: GPIOBank, chips: list[EmulatedAD7606], *, convst: str, reset: str, range_line: str):
        self.bank, self.chips = bank, chips
        self.convst, self.reset_line, self.range_line = convst, reset, range_line
        self._edges: list[float] = []             # BUSY falling edges a waiter may not have taken yet
        self._range_changed_at: tuple[float, int] | None = None
        bank.watch(convst, self._convst_changed)
        bank.watch(reset, self._reset_changed)
        bank.watch(range_line, self._range_changed)

    def _instant(self) -> tuple[float, int]:
        return self.bank.clock.monotonic(), len(self.bank.log)

    @property
    def full_scale_v(self) -> float:
        return FULL_SCALES_V[0] if self.bank.driven.get(self.range_line, 0) else FULL_SCALES_V[1]

    def _convst_changed(self, old: int, new: int) -> None:
        if not (old == 0 and new == 1):
            return
        if self._range_changed_at == self._instant():
            raise EmulatorViolation("AD7606: RANGE changed in the same call as the CONVST rising edge (no setup "
                                    "time); change RANGE in an earlier call")
        now = self.bank.clock.monotonic()
        started = [chip.start(now, self.full_scale_v) for chip in self.chips]
        if any(started):
            self._edges.append(now + max(chip.conversion_s for chip in self.chips))

    def _reset_changed(self, old: int, new: int) -> None:
        if old == 1 and new == 0:
            for chip in self.chips:
                chip.reset_pulse()

    def _range_changed(self, old: int, new: int) -> None:
        now = self.bank.clock.monotonic()
        if any(chip.busy(now) for chip in self.chips):
            raise EmulatorViolation("AD7606: RANGE changed during a conversion; change it between conversions")
        self._range_changed_at = self._instant()

    def take_due(self, now: float) -> None:
        """Before the analogue state changes: each converter samples what it must up to now."""
        for chip in self.chips:
            chip.take_due(now)

    # -- BUSY ----------------------------------------------------------------------------
    def level(self, now: float) -> int:
        return int(any(chip.busy(now) for chip in self.chips))

    def next_edge(self, after: float, edge: str) -> float | None:
        """The first falling edge of BUSY later than ``after`` (it may be past); older ones are forgotten."""
        while self._edges and self._edges[0] <= after:
            self._edges.pop(0)
        return self._edges[0] if edge == FALLING and self._edges else None
