"""MCP9808 emulator: pointer-addressed registers and conversions timed on the simulated clock.

A one-byte write sets the register pointer; a longer write sets the pointer and
writes the register (two bytes MSB first, one for the resolution register);
reads return the pointed register MSB first. The pointer's bits 7..4 must be 0
and pointers 0x09..0x0F reach test registers, so either is an
:class:`EmulatorViolation`. Writes to the read-only registers (0x00, 0x05..0x07)
are ignored as the chip ignores them, with a note in ``warnings``.

Conversions: the chip converts continuously and the T_A register holds the last
completed result, loaded every t_conv (250 ms at the power-on resolution 0x03).
The emulator samples ``temperature_c(t)`` at each completion time and floors it
to the resolution step (an assumption: the datasheet does not say how the ADC
rounds). Before the first conversion completes T_A reads its power-on value 0
(0 degC, the register's documented reset value). Changing the resolution, or
leaving shutdown (CONFIG bit 8), restarts the conversion schedule; in shutdown
T_A holds its last value. The lock and alert-output bits of CONFIG are stored
but not acted on; the alert flags T_A<15:13> are computed from the limits.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from appliance.drivers.emulated.buses import EmulatorViolation, I2CChipEmulator
from appliance.drivers.emulated.clock import SimulatedClock

CONFIG, T_UPPER, T_LOWER, T_CRIT, T_A, MANUFACTURER, DEVICE, RESOLUTION = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x08
SHDN = 1 << 8
WRITABLE_MASK = {CONFIG: 0x07FF, T_UPPER: 0x1FFC, T_LOWER: 0x1FFC, T_CRIT: 0x1FFC, RESOLUTION: 0x03}
CONVERSION_S = (0.030, 0.065, 0.130, 0.250)
"""Typical t_conv at resolution 0x00 (0.5 degC), 0x01, 0x02 and 0x03 (0.0625 degC)."""
RFU_VALUE = 0x001F


def _signed13(word: int) -> int:
    code = word & 0x1FFF
    return code - 0x2000 if code & 0x1000 else code


class EmulatedMCP9808(I2CChipEmulator):
    """An MCP9808 whose die temperature at simulated time t is ``temperature_c(t)``.

    ``manufacturer_id`` and ``device_revision`` (registers 0x06 and 0x07) may be
    overridden to emulate another chip at the same address.
    """

    name = "MCP9808"
    manufacturer_id = 0x0054
    device_revision = 0x0400

    def __init__(self, clock: SimulatedClock, temperature_c: Callable[[float], float], *, address: int = 0x18):
        self.clock = clock
        self.temperature_c = temperature_c
        self.address = address
        self.warnings: list[str] = []
        self.reset()

    def reset(self) -> None:
        """Power-on: limits and CONFIG 0, resolution 0x03, T_A 0 until the first conversion completes."""
        self.pointer = 0
        self.registers = {CONFIG: 0, T_UPPER: 0, T_LOWER: 0, T_CRIT: 0, RESOLUTION: 0x03}
        self._held_code = 0
        self._series_start_s = self.clock.monotonic()

    def write(self, data: bytes) -> None:
        if not data:
            return
        pointer = data[0]
        if pointer & 0xF0 or pointer > RESOLUTION:
            raise EmulatorViolation(f"MCP9808: register pointer 0x{pointer:02X} is not a user register "
                                    "(bits 7..4 must be 0; 0x09..0x0F are test registers)")
        self.pointer = pointer
        payload = data[1:]
        if not payload:
            return
        if pointer not in WRITABLE_MASK:
            self.warnings.append(f"write of {payload.hex()} to read-only register 0x{pointer:02X} ignored")
            return
        width = 1 if pointer == RESOLUTION else 2
        if len(payload) != width:
            raise EmulatorViolation(f"MCP9808: register 0x{pointer:02X} takes {width} data byte(s), "
                                    f"got {len(payload)}")
        value = int.from_bytes(payload, "big") & WRITABLE_MASK[pointer]
        if pointer == RESOLUTION or (pointer == CONFIG and (value ^ self.registers[CONFIG]) & SHDN):
            self._restart_conversions()
        self.registers[pointer] = value

    def read(self, n: int) -> bytes:
        width = 1 if self.pointer == RESOLUTION else 2
        if n > width:
            raise EmulatorViolation(f"MCP9808: read of {n} bytes from the {width}-byte register 0x{self.pointer:02X}")
        return self._value(self.pointer).to_bytes(width, "big")[:n]

    def _value(self, pointer: int) -> int:
        if pointer in self.registers:
            return self.registers[pointer]
        if pointer == T_A:
            return self._ambient_word()
        return {MANUFACTURER: self.manufacturer_id, DEVICE: self.device_revision}.get(pointer, RFU_VALUE)

    def _ambient_word(self) -> int:
        code = self._current_code()
        flags = 0
        if code >= _signed13(self.registers[T_CRIT]):
            flags |= 1 << 15
        if code > _signed13(self.registers[T_UPPER]):
            flags |= 1 << 14
        if code < _signed13(self.registers[T_LOWER]):
            flags |= 1 << 13
        return flags | (code & 0x1FFF)

    def _current_code(self) -> int:
        """T_A<12:0> as a signed count of 1/16 degC: the last completed conversion."""
        if self.registers[CONFIG] & SHDN:
            return self._held_code
        period_s = CONVERSION_S[self.registers[RESOLUTION]]
        done = math.floor((self.clock.monotonic() - self._series_start_s) / period_s)
        if done < 1:
            return self._held_code
        sample_c = self.temperature_c(self._series_start_s + done * period_s)
        code = max(-0x1000, min(0x0FFF, math.floor(sample_c * 16)))
        return code - code % (8 >> self.registers[RESOLUTION])

    def _restart_conversions(self) -> None:
        self._held_code = self._current_code()
        self._series_start_s = self.clock.monotonic()
