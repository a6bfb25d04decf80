"""The board of a real front end: SPI through spidev, I2C through smbus2, GPIO through gpiod, real time.

Each bus is opened on first request, so a machine without one of the
libraries (or without the device node) fails only when that bus is asked for,
with an error naming what to install or enable.
"""

from __future__ import annotations

from appliance.drivers.bus import Board, Clock, LineRequest
from appliance.drivers.linux_gpio import LinuxGPIOLines
from appliance.drivers.linux_i2c import LinuxI2CBus
from appliance.drivers.linux_spi import LinuxSPIDevice


class LinuxBoard(Board):
    """The Raspberry Pi's buses; ``gpio_chip`` (from the configuration) pins GPIO to one chip instead of searching."""

    clock = Clock()

    def __init__(self, *, gpio_chip: str | None = None):
        super().__init__()
        self.gpio_chip = gpio_chip

    def _open_spi(self, bus: int, chip_select: int, mode: int, max_speed_hz: int) -> LinuxSPIDevice:
        return LinuxSPIDevice(bus, chip_select, mode=mode, max_speed_hz=max_speed_hz)

    def _open_i2c(self, bus: int) -> LinuxI2CBus:
        return LinuxI2CBus(bus)

    def _request_lines(self, request: LineRequest, consumer: str) -> LinuxGPIOLines:
        return LinuxGPIOLines(request, consumer=consumer, chip_path=self.gpio_chip)
