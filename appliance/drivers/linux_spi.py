"""One SPI chip select on Linux through spidev (``/dev/spidevB.C``).

Each :meth:`LinuxSPIDevice.transfer` is a single ``xfer2`` call, which spidev
turns into one ``spi_ioc_transfer``: chip select stays asserted for the whole
frame, as the front end's chips require. Errors are turned into the appliance's
own (:class:`~appliance.errors.DeviceMissing` with a hint on how to enable the
node, :class:`~appliance.errors.TransferFailed` naming the device) so a failure
on a Pi reads the same as one under emulation.
"""

from __future__ import annotations

import errno

from appliance.drivers.bus import SPIDevice, os_error_to_bus_error
from appliance.errors import BackendUnavailable, BusError, DeviceMissing

try:
    import spidev
except ImportError:
    spidev = None


class LinuxSPIDevice(SPIDevice):
    """The SPI device ``/dev/spidev{bus}.{chip_select}``, opened in ``mode`` at ``max_speed_hz``, 8-bit words."""

    def __init__(self, bus: int, chip_select: int, *, mode: int, max_speed_hz: int):
        if spidev is None:
            raise BackendUnavailable("SPI needs the spidev package: pip install spidev "
                                     "(it builds a C extension, so gcc and python3-dev must be installed)")
        self.bus, self.chip_select = bus, chip_select
        self.name = f"/dev/spidev{bus}.{chip_select}"
        self.mode, self.max_speed_hz = mode, max_speed_hz
        device = spidev.SpiDev()
        try:
            device.open(bus, chip_select)
        except FileNotFoundError as exc:
            raise DeviceMissing(f"{self.name} does not exist: is SPI enabled? The appliance's image gives SPI1 "
                                "one chip select unless built for a profile with three (build-image.sh --profile, "
                                "image-build/README.md); Raspberry Pi OS needs dtparam=spi=on in config.txt, and "
                                "SPI1 an overlay (such as spi1-3cs)") from exc
        except OSError as exc:
            raise self._error(exc) from exc
        try:
            device.mode = mode
            device.max_speed_hz = max_speed_hz
            device.bits_per_word = 8
        except OSError as exc:
            device.close()
            raise self._error(exc) from exc
        self._device = device

    def _error(self, exc: OSError) -> Exception:
        if exc.errno == errno.EACCES:
            return BusError(f"SPI {self.name}: permission denied; add the user to the spi group "
                            "(sudo usermod -aG spi USER) and log in again")
        return os_error_to_bus_error(f"SPI {self.name}", exc)

    def transfer(self, data: bytes) -> bytes:
        """Clock ``data`` out in one chip-select frame (one ``xfer2``); return the bytes clocked in."""
        if self._device is None:
            raise BusError(f"SPI {self.name}: transfer after close")
        try:
            received = self._device.xfer2(list(data))
        except OSError as exc:
            raise self._error(exc) from exc
        return bytes(received)

    def close(self) -> None:
        """Close the device node; idempotent."""
        if self._device is not None:
            self._device.close()
            self._device = None
