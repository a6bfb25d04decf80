"""MCP4017 emulator: a 7-bit volatile wiper register at I2C address 0x2F.

Modelled on the MCP4017/18/19 datasheet (DS22147A, section 5.4 and figure 5-14):

* every data byte of a write message is written to the wiper as it is
  acknowledged, so in a multi-byte write the last byte wins;
* the MSb of each written byte is a don't care (the register is 7 bits wide),
  so 0xC0 sets the wiper to 0x40;
* a read returns the wiper as ``0ddddddd`` for every byte the master asks for;
* power-on (and brown-out) loads mid-scale, 0x3F.
"""

from __future__ import annotations

from collections.abc import Callable

from appliance.drivers.emulated.buses import I2CChipEmulator, notify

POWER_ON_WIPER = 0x3F


class EmulatedMCP4017(I2CChipEmulator):
    """One MCP4017; :attr:`wiper` is its register (0..127), ``listeners`` are told after it changes."""

    name = "MCP4017"
    address = 0x2F

    def __init__(self):
        self.wiper = POWER_ON_WIPER
        self.listeners: list[Callable[[], None]] = []

    def write(self, data: bytes) -> None:
        for byte in data:
            self._set(byte & 0x7F)

    def read(self, n: int) -> bytes:
        return bytes([self.wiper & 0x7F]) * n

    def reset(self) -> None:
        """Power-on: wiper at mid-scale."""
        self._set(POWER_ON_WIPER)

    def _set(self, wiper: int) -> None:
        changed = wiper != self.wiper
        self.wiper = wiper
        if changed:
            notify(self.listeners)
