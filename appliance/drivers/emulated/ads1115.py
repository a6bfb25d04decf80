"""Register-level ADS1115: pointer register, single-shot conversions in simulated time, ALERT/RDY.

The data sheet's facts (TI SBAS444D; :mod:`appliance.drivers.ads1115` lists the sections):
power-on config 0x8583 (AIN0-AIN1, +/-2.048 V, single shot, 128 SPS, comparator off),
Lo_thresh 0x8000, Hi_thresh 0x7FFF, conversion 0. Writing OS = 1 while idle starts one
conversion and OS reads 0 until it ends; written during a conversion it does nothing. A
conversion samples the input at its start and its end and averages the two (the
delta-sigma modulator integrates over the period), so a driver that starts converting
before the RMS converter has settled reads a wrong value.

ALERT/RDY in conversion-ready mode (Hi_thresh MSB 1, Lo_thresh MSB 0, COMP_QUE not 11)
outputs OS, asserted low with COMP_POL 0: it rises when a conversion starts and falls
when it ends, and falls at once when the mode is entered while the chip is idle (the
config write of a driver's self-test). Each change is kept as an edge at its time, so
the line's queue holds it until a wait takes it or a drain discards it, as the kernel's
does. Otherwise the pin is released (COMP_QUE 11; the threshold comparator is not
modelled). The pin is open drain: the line must be requested with its pull-up.
A ``stuck_code`` makes every conversion return that code, as a latched-up chip or a
broken input would.
"""

from __future__ import annotations

import errno
from collections.abc import Callable
from contextlib import contextmanager

import numpy as np

from appliance.drivers.bus import FALLING, RISING
from appliance.drivers.emulated.buses import EmulatorViolation, I2CChipEmulator, InputSource

FULL_SCALES_V = (6.144, 4.096, 2.048, 1.024, 0.512, 0.256, 0.256, 0.256)
DATA_RATES_SPS = (8, 16, 32, 64, 128, 250, 475, 860)
INPUT_PAIRS = (("AIN0", "AIN1"), ("AIN0", "AIN3"), ("AIN1", "AIN3"), ("AIN2", "AIN3"),
               ("AIN0", None), ("AIN1", None), ("AIN2", None), ("AIN3", None))
POWER_ON = {0x00: 0x0000, 0x01: 0x8583, 0x02: 0x8000, 0x03: 0x7FFF}
OS = 0x8000
COMP_POL = 0x0008
COMP_QUE_DISABLED = 0x0003


class EmulatedADS1115(I2CChipEmulator, InputSource):
    """``pin_volts(name, t)`` gives the voltage on AIN0..AIN3 at time ``t``."""

    name = "ADS1115"
    open_drain = True

    def __init__(self, clock, pin_volts: Callable[[str, float], float], *, address: int = 0x48,
                 oscillator_slow: float = 1.03, noise_lsb: float = 0.0, seed: int = 0):
        self.clock, self.pin_volts, self.address = clock, pin_volts, address
        self.oscillator_slow, self.noise_lsb = oscillator_slow, noise_lsb
        self._rng = np.random.default_rng(seed)
        self.stuck_code: int | None = None
        self.reset()

    def reset(self) -> None:
        """Power on: registers at their reset values, ALERT/RDY released, no edge kept from before."""
        self.registers = dict(POWER_ON)
        self._edges: list[tuple[float, str]] = []      # ALERT/RDY's changes not yet read off the line
        self.pointer = 0x00
        self.conversion: tuple[float, float, int] | None = None   # start, end, config of the running one
        self.first_sample_v = 0.0
        self.warnings: list[str] = []
        self.conversions = 0

    # -- I2C ---------------------------------------------------------------------------
    def write(self, data: bytes) -> None:
        if not data or data[0] > 0x03:
            raise OSError(errno.EREMOTEIO, "pointer register out of range: not acknowledged")
        if len(data) == 1:
            self.pointer = data[0]
            return
        if len(data) != 3:
            raise EmulatorViolation(f"ADS1115: a register write is [pointer, MSB, LSB], got {len(data)} bytes")
        self.pointer = data[0]
        value = data[1] << 8 | data[2]
        if self.pointer == 0x00:
            self.warnings.append("write to the read-only conversion register ignored")
            return
        self._finish_if_done()
        with self._pin_edges(self.clock.monotonic()):
            if self.pointer == 0x01:
                self.registers[0x01] = value & 0x7FFF | (self.registers[0x01] & OS)
                if value & OS and self.conversion is None:
                    self._start(value)
            else:
                self.registers[self.pointer] = value

    def read(self, n: int) -> bytes:
        self._finish_if_done()
        value = self.registers[self.pointer]
        return bytes([value >> 8, value & 0xFF] * ((n + 1) // 2))[:n]

    # -- conversions -------------------------------------------------------------------
    def period_s(self, config: int) -> float:
        return self.oscillator_slow / DATA_RATES_SPS[(config >> 5) & 0x7]

    def _start(self, config: int) -> None:
        now = self.clock.monotonic()
        self.registers[0x01] &= ~OS              # OS reads 0 while converting
        self.conversion = (now, now + self.period_s(config), config)
        self.first_sample_v = self._input(config, now)

    def _input(self, config: int, t: float) -> float:
        positive, negative = INPUT_PAIRS[(config >> 12) & 0x7]
        volts = self.pin_volts(positive, t)
        return volts - self.pin_volts(negative, t) if negative else volts

    def _finish_if_done(self) -> None:
        if self.conversion is None or self.clock.monotonic() < self.conversion[1]:
            return
        _, end, config = self.conversion
        volts = 0.5 * (self.first_sample_v + self._input(config, end))
        lsb = FULL_SCALES_V[(config >> 9) & 0x7] / 32768
        code = round(volts / lsb + self.noise_lsb * self._rng.standard_normal())
        if self.stuck_code is not None:
            code = self.stuck_code
        with self._pin_edges(end):
            self.registers[0x00] = int(np.clip(code, -32768, 32767)) & 0xFFFF
            self.registers[0x01] |= OS
            self.conversion = None
        self.conversions += 1

    # -- ALERT/RDY -----------------------------------------------------------------------
    def _ready_mode(self) -> bool:
        return (self.registers[0x01] & COMP_QUE_DISABLED) != COMP_QUE_DISABLED \
            and bool(self.registers[0x03] & 0x8000) and not self.registers[0x02] & 0x8000

    def _pin(self, idle: bool) -> int:
        """ALERT/RDY's level with OS at ``idle``: in conversion-ready mode OS, active low unless COMP_POL."""
        if not self._ready_mode():
            return 1
        return int(idle) if self.registers[0x01] & COMP_POL else int(not idle)

    def _pin_now(self) -> int:
        return self._pin(bool(self.registers[0x01] & OS))

    @contextmanager
    def _pin_edges(self, when: float):
        """Keep the edge ALERT/RDY makes at ``when`` if what runs inside changes it."""
        before = self._pin_now()
        yield
        after = self._pin_now()
        if after != before:
            self._edges.append((when, RISING if after else FALLING))

    def level(self, now: float) -> int:
        self._finish_if_done()
        return self._pin_now()

    def next_edge(self, after: float, edge: str) -> float | None:
        """The first ``edge`` later than ``after``: one kept, or the end of the running conversion."""
        self._finish_if_done()
        self._edges = [(when, kind) for when, kind in self._edges if when > after]
        kept = [when for when, kind in self._edges if kind == edge]
        if kept:
            return kept[0]
        at_end = self._pin(True)
        if self.conversion is not None and at_end != self._pin(False) and edge == (RISING if at_end else FALLING):
            return self.conversion[1]
        return None
