"""MCP4017 7-bit I2C digital rheostat: sets the excitation amplitude before the VCCS.

The chip has no register address: a write is an SMBus send-byte of the wiper
value and a read is a receive-byte. Every write is read back, because a wrong
wiper means a wrong excitation current and so wrong readings for the whole frame.
"""

from __future__ import annotations

from appliance.drivers.bus import I2CBus
from appliance.errors import ChipReadbackMismatch


class MCP4017:
    """One MCP4017 at ``address`` on ``i2c``; wiper positions 0 (terminal B) to 127 (terminal A)."""

    POSITIONS = 128

    def __init__(self, i2c: I2CBus, *, address: int = 0x2F):
        self.i2c = i2c
        self.address = address

    def set_wiper(self, position: int) -> None:
        """Move the wiper to ``position`` and confirm it by reading it back."""
        if isinstance(position, bool) or not isinstance(position, int) or not 0 <= position < self.POSITIONS:
            raise ValueError(f"MCP4017 wiper position {position!r} is out of range 0..{self.POSITIONS - 1}")
        self.i2c.write_byte(self.address, position)
        read = self.wiper()
        if read != position:
            raise ChipReadbackMismatch(f"MCP4017 at I2C address 0x{self.address:02X} on {self.i2c.name}: "
                                       f"wrote wiper {position}, read back {read}")

    def wiper(self) -> int:
        """The wiper position the chip reports."""
        return self.i2c.read_byte(self.address)
