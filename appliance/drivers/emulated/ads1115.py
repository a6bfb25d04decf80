"""Register-level ADS1115: pointer register, single-shot conversions in simulated time, ALERT/RDY.

Power-on state per the datasheet: config 0x8583 (AIN0-AIN1, +/-2.048 V, single
shot, 128 SPS, comparator off), Lo_thresh 0x8000, Hi_thresh 0x7FFF, conversion 0
[recall: verify]. A conversion samples the input at its start and its end and
averages the two (the delta-sigma modulator integrates over the period), so a
driver that starts converting before the RMS converter has settled reads a wrong
value. ALERT/RDY, in conversion-ready mode (Hi_thresh MSB 1, Lo_thresh MSB 0,
COMP_QUE not 11, COMP_POL 0), is high while converting and falls at the end
[recall: verify whether single-shot holds it low until the next start; modelled so].
A ``stuck_code`` makes every conversion return that code, as a latched-up chip or a
broken input would.
"""

from __future__ import annotations

import errno
from collections.abc import Callable

import numpy as np

from appliance.drivers.bus import FALLING
from appliance.drivers.emulated.buses import EmulatorViolation, I2CChipEmulator, InputSource

FULL_SCALES_V = (6.144, 4.096, 2.048, 1.024, 0.512, 0.256, 0.256, 0.256)
DATA_RATES_SPS = (8, 16, 32, 64, 128, 250, 475, 860)
INPUT_PAIRS = (("AIN0", "AIN1"), ("AIN0", "AIN3"), ("AIN1", "AIN3"), ("AIN2", "AIN3"),
               ("AIN0", None), ("AIN1", None), ("AIN2", None), ("AIN3", None))
POWER_ON = {0x00: 0x0000, 0x01: 0x8583, 0x02: 0x8000, 0x03: 0x7FFF}


class EmulatedADS1115(I2CChipEmulator, InputSource):
    """``pin_volts(name, t)`` gives the voltage on AIN0..AIN3 at time ``t``."""

    name = "ADS1115"

    def __init__(self, clock, pin_volts: Callable[[str, float], float], *, address: int = 0x48,
                 oscillator_slow: float = 1.03, noise_lsb: float = 0.0, seed: int = 0):
        self.clock, self.pin_volts, self.address = clock, pin_volts, address
        self.oscillator_slow, self.noise_lsb = oscillator_slow, noise_lsb
        self._rng = np.random.default_rng(seed)
        self.stuck_code: int | None = None
        self.reset()

    def reset(self) -> None:
        self.registers = dict(POWER_ON)
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
        if self.pointer == 0x01:
            self.registers[0x01] = value & 0x7FFF | (self.registers[0x01] & 0x8000)
            if value & 0x8000 and self.conversion is None:
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
        self.registers[0x01] &= 0x7FFF           # OS reads 0 while converting
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
        self.registers[0x00] = int(np.clip(code, -32768, 32767)) & 0xFFFF
        self.registers[0x01] |= 0x8000
        self.conversion = None
        self.conversions += 1

    # -- ALERT/RDY -----------------------------------------------------------------------
    def _ready_mode(self) -> bool:
        config = self.registers[0x01]
        return (config & 0x3) != 0x3 and not config & 0x8 and self.registers[0x03] & 0x8000 \
            and not self.registers[0x02] & 0x8000

    def level(self, now: float) -> int:
        if not self._ready_mode():
            return 1
        self._finish_if_done()
        return 1 if self.conversion is not None else 0

    def next_edge(self, after: float, edge: str) -> float | None:
        if edge == FALLING and self._ready_mode() and self.conversion is not None:
            return max(after, self.conversion[1])
        return None
