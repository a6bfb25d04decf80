"""MCP9808 I2C temperature sensor: the board temperature, for drift compensation and over-heat alarms.

Registers are selected by a pointer byte and are 16 bits, most significant byte
first (read as an SMBus read word with its bytes swapped). The ambient
temperature register (0x05) carries three alert-comparison flags in bits 15..13,
the sign in bit 12 and the temperature in 1/16 degC below it, so the 13 bits
12..0 are one two's-complement number. The flags are set whenever the
temperature is beyond the limit registers (all 0 degC at power-on, so at room
temperature they read as set) and must be masked off.
"""

from __future__ import annotations

from appliance.drivers.bus import I2CBus
from appliance.errors import ChipReadbackMismatch

AMBIENT = 0x05
MANUFACTURER_ID = 0x06
DEVICE_ID = 0x07

EXPECTED_MANUFACTURER = 0x0054
EXPECTED_DEVICE = 0x04


def decode_ambient(word: int) -> float:
    """Degrees C from a raw T_A register word.

    >>> decode_ambient(0xC179)  # alert flags 15 and 14 set, +23.5625 degC
    23.5625
    >>> decode_ambient(0x1FAC)
    -5.25
    """
    code = word & 0x1FFF
    if code & 0x1000:
        code -= 0x2000
    return code / 16


class MCP9808:
    """One MCP9808 at ``address`` (0x18 with A2..A0 low) on ``i2c``."""

    def __init__(self, i2c: I2CBus, *, address: int = 0x18):
        self.i2c = i2c
        self.address = address

    def check_identity(self) -> int:
        """Confirm a MCP9808 answers (manufacturer 0x0054, device 0x04); return its silicon revision.

        Raises :class:`~appliance.errors.ChipReadbackMismatch` naming what was read otherwise.
        """
        manufacturer = self._read16(MANUFACTURER_ID)
        device, revision = divmod(self._read16(DEVICE_ID), 0x100)
        if manufacturer != EXPECTED_MANUFACTURER or device != EXPECTED_DEVICE:
            raise ChipReadbackMismatch(
                f"MCP9808 at I2C address 0x{self.address:02X} on {self.i2c.name}: read manufacturer ID "
                f"0x{manufacturer:04X} and device ID 0x{device:02X}, expected 0x{EXPECTED_MANUFACTURER:04X} "
                f"and 0x{EXPECTED_DEVICE:02X}")
        return revision

    def temperature_c(self) -> float:
        """The last completed conversion, in degC (resolution 0.0625 degC at the power-on setting)."""
        return decode_ambient(self._read16(AMBIENT))

    def _read16(self, register: int) -> int:
        return self.i2c.read_word_swapped(self.address, register)
