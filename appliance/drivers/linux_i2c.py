"""One I2C adapter on Linux through smbus2 (``/dev/i2c-N``).

The three primitives are ``i2c_rdwr`` transactions built from ``i2c_msg``
messages, so :meth:`LinuxI2CBus.write_read` is one transaction with a repeated
start. The SMBus helpers use smbus2's native SMBus calls instead, which more
adapters support than raw ``I2C_RDWR`` (an SMBus-only controller, or the
kernel's ``i2c-stub`` the real-kernel tests run on, refuses it with EOPNOTSUPP). Every OSError becomes the appliance's
error naming bus and address: a chip that does not acknowledge (errno 121 on
the Pi's controller) gives :class:`~appliance.errors.TransferFailed` with errno 121.
"""

from __future__ import annotations

import errno

from appliance.drivers.bus import I2CBus, os_error_to_bus_error
from appliance.errors import BackendUnavailable, BusError, DeviceMissing

try:
    from smbus2 import SMBus, i2c_msg
except ImportError:
    SMBus = i2c_msg = None      # type: ignore[misc, assignment]  # absent off Linux; checked before use

SMBUS_BLOCK_MAX = 32
"""The most bytes one SMBus I2C-block call carries; longer blocks go as plain I2C transactions."""


class LinuxI2CBus(I2CBus):
    """The I2C adapter ``/dev/i2c-{bus}``."""

    def __init__(self, bus: int):
        if SMBus is None:
            raise BackendUnavailable("I2C needs the smbus2 package: pip install smbus2")
        self.number = bus
        self.name = f"/dev/i2c-{bus}"
        try:
            self._smbus: SMBus | None = SMBus(bus)
        except FileNotFoundError as exc:
            raise DeviceMissing(f"{self.name} does not exist: is I2C enabled "
                                "(dtparam=i2c_arm=on in config.txt, or raspi-config)?") from exc
        except OSError as exc:
            if exc.errno == errno.EACCES:
                raise BusError(f"I2C {self.name}: permission denied; add the user to the i2c group "
                               "(sudo usermod -aG i2c USER) and log in again") from exc
            raise os_error_to_bus_error(f"I2C {self.name}", exc) from exc

    def _call(self, address: int, method: str, *args):
        """Call the smbus2 method ``method`` for a transfer to ``address``, translating its OSError."""
        if self._smbus is None:
            raise BusError(f"I2C bus {self.number}: used after close")
        try:
            return getattr(self._smbus, method)(*args)
        except OSError as exc:
            raise os_error_to_bus_error(f"I2C bus {self.number} address 0x{address:02X}", exc) from exc

    def write(self, address: int, data: bytes) -> None:
        """One write message of ``data`` to ``address``."""
        self._call(address, "i2c_rdwr", i2c_msg.write(address, bytes(data)))

    def read(self, address: int, n: int) -> bytes:
        """One read message of ``n`` bytes from ``address``."""
        message = i2c_msg.read(address, n)
        self._call(address, "i2c_rdwr", message)
        return bytes(message)

    def write_read(self, address: int, data: bytes, n: int) -> bytes:
        """Write ``data``, repeated start, read ``n`` bytes: one ``i2c_rdwr`` with two messages."""
        message = i2c_msg.read(address, n)
        self._call(address, "i2c_rdwr", i2c_msg.write(address, bytes(data)), message)
        return bytes(message)

    def write_byte(self, address: int, value: int) -> None:
        """SMBus send byte."""
        self._call(address, "write_byte", address, value)

    def read_byte(self, address: int) -> int:
        """SMBus receive byte."""
        return self._call(address, "read_byte", address)

    def write_byte_data(self, address: int, register: int, value: int) -> None:
        """SMBus write byte: register then value."""
        self._call(address, "write_byte_data", address, register, value)

    def read_byte_data(self, address: int, register: int) -> int:
        """SMBus read byte: register, repeated start, one byte."""
        return self._call(address, "read_byte_data", address, register)

    def write_word_swapped(self, address: int, register: int, value: int) -> None:
        """SMBus write word, given the value byte-swapped so the chip receives its MSB first."""
        self._call(address, "write_word_data", address, register, _swap_bytes(value))

    def read_word_swapped(self, address: int, register: int) -> int:
        """SMBus read word, byte-swapped back: the chip sent its MSB first, SMBus takes the first byte as low."""
        return _swap_bytes(self._call(address, "read_word_data", address, register))

    def write_block(self, address: int, register: int, data: bytes) -> None:
        """SMBus I2C-block write; more than 32 bytes go as one I2C write message."""
        if len(data) > SMBUS_BLOCK_MAX:
            super().write_block(address, register, data)
            return
        self._call(address, "write_i2c_block_data", address, register, list(data))

    def read_block(self, address: int, register: int, n: int) -> bytes:
        """SMBus I2C-block read; more than 32 bytes go as one write-read transaction."""
        if n > SMBUS_BLOCK_MAX:
            return super().read_block(address, register, n)
        return bytes(self._call(address, "read_i2c_block_data", address, register, n))

    def close(self) -> None:
        """Close the adapter's device node; idempotent."""
        if self._smbus is not None:
            self._smbus.close()
            self._smbus = None


def _swap_bytes(word: int) -> int:
    return (word & 0xFF) << 8 | word >> 8
