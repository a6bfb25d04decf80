"""What the host computer offers the front end: Raspberry Pi boards and the systems that run on them, as data.

A profile names GPIO lines as the kernel names them, and which names a header pin carries depends on the
board *and* on the kernel's device tree: the mainline trees name GPIO 4 "GPIO_GCLK" on a Pi 3 or 4, the
Raspberry Pi kernel's tree for the Pi 4 names it "GPIO4". So a :class:`HostBoard` lists its header lines
(GPIO 0..27, by BCM number) per kernel flavour, and a :class:`System` says which kernel it boots and which
buses its config.txt and overlays enable, since an enabled bus claims its pins from every other user.

Every fact is taken from the file cited beside it (repository and path, as read); what could not be read
is ``None`` and is not checked, never guessed. Sources:

* mainline line names: torvalds/linux arch/arm/boot/dts/broadcom/bcm2837-rpi-3-b.dts,
  bcm2837-rpi-3-b-plus.dts and bcm2711-rpi-4-b.dts (``&gpio`` ``gpio-line-names``);
* Raspberry Pi kernel line names: raspberrypi/linux arch/arm/boot/dts/broadcom/bcm2710-rpi-3-b.dts (still
  the mainline names in the version read), bcm2710-rpi-3-b-plus.dts and bcm2711-rpi-4-b.dts (``&gpio``),
  arch/arm64/boot/dts/broadcom/bcm2712-rpi-5-b.dts (``&rp1_gpio``);
* SPI0 pins: raspberrypi/linux bcm2710-rpi-3-b.dts (``spi0_pins`` 9 10 11, ``cs-gpios`` 8 then 7), the same
  chip selects in bcm2711-rpi-4-b.dts; SPI1 pins: raspberrypi/linux arch/arm/boot/dts/overlays/
  spi1-1cs-overlay.dts and spi1-3cs-overlay.dts (19 20 21 in ALT4, chip selects 18, 17, 16); I2C1 pins:
  ``i2c1_pins`` 2 3 in bcm2710-rpi-3-b.dts;
* I2C clock: the mainline trees of Debian's kernels (linux-image-arm64 6.1 and 7.3, linux-image-armmp-lpae
  6.1, read with dtc) give ``i2c@7e804000`` ``clock-frequency = <100000>``, and
  torvalds/linux drivers/i2c/busses/i2c-bcm2835.c falls back to the same standard-mode 100 kHz without it;
* the Pi 5 under Debian: linux-image-7.3.4+deb13-arm64 (trixie-backports, the first Debian kernel with RP1's
  drivers) ships bcm2712-rpi-5-b.dtb with RP1's I2C controllers, GPIO and Ethernet, but no SPI node, and its
  configuration has ``# CONFIG_SPI_DESIGNWARE is not set``: no driver for RP1's SPI controllers;
* SPI modes: torvalds/linux drivers/spi/spi-bcm2835aux.c sets ``mode_bits = SPI_CPOL | SPI_CS_HIGH |
  SPI_NO_CS``, without SPI_CPHA, so the SPI core refuses CPHA = 1 (modes 1 and 3) with EINVAL; the
  DesignWare driver RP1's SPI uses (drivers/spi/spi-dw-core.c, ``dw_spi_add_host``) and spi-bcm2835.c
  (``BCM2835_SPI_MODE_BITS``, SPI0 on a Pi 3 or 4) both include SPI_CPOL | SPI_CPHA: all four modes.

Not verified: the mainline names on a Pi 5 (torvalds/linux bcm2712-rpi-5-b.dts and bcm2712-rpi-5-b-ovl-rp1.dts
give ``&rp1_gpio`` none; rp1-common.dtsi was not read), the Pi 5's bus pins (RP1's pin functions were not
read), and every controller's clock limit (no source read states one).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

HEADER_GPIOS = 28
"""GPIO 0..27 reach the 40-pin header on every board here."""
KERNELS = ("mainline", "raspberrypi")

_MAINLINE_BCM283X = ("ID_SDA", "ID_SCL", "SDA1", "SCL1", "GPIO_GCLK", "GPIO5", "GPIO6", "SPI_CE1_N", "SPI_CE0_N",
                     "SPI_MISO", "SPI_MOSI", "SPI_SCLK", "GPIO12", "GPIO13", "TXD1", "RXD1",
                     *(f"GPIO{n}" for n in range(16, 28)))
"""Identical in the mainline trees of the Pi 3B, 3B+ and 4B, and in the Raspberry Pi kernel's Pi 3B tree as read."""
_GPIO_NUMBERED = ("ID_SDA", "ID_SCL", *(f"GPIO{n}" for n in range(2, 28)))
"""The Raspberry Pi kernel's names on a Pi 3B+ and 4B (``&gpio``) and a Pi 5 (``&rp1_gpio``)."""


@dataclass(frozen=True)
class SPIController:
    """One SPI controller on the header: its driver, the modes it accepts and its MISO, MOSI and SCLK pins."""

    bus: int
    driver: str
    modes: frozenset[int] | None
    data_pins: tuple[int, int, int] | None


@dataclass(frozen=True)
class HostBoard:
    """A computer the appliance runs on: its header lines per kernel flavour, its SPI controllers and I2C pins."""

    name: str
    model: str
    compatible: str | None
    gpio_controller: str
    line_names: Mapping[str, tuple[str, ...] | None]
    spi: Mapping[int, SPIController]
    i2c_pins: Mapping[int, tuple[int, int] | None]

    def names(self, kernel: str) -> tuple[str, ...] | None:
        """The names of GPIO 0..27 under ``kernel``, or None where they were not verified."""
        return self.line_names.get(kernel)


@dataclass(frozen=True)
class System:
    """An operating system on the host: the kernel flavour it boots and the buses its boot configuration enables.

    ``spi_chip_selects`` maps each enabled SPI bus to the GPIO of each chip select (CE0 first);
    ``i2c_clock_hz`` gives the clock of each enabled I2C bus; ``reserved`` names other header pins the system
    takes for itself. ``boards`` are the host boards the system is built for (empty: any); ``lacks`` says
    what it cannot give a profile, and why.
    """

    name: str
    kernel: str
    spi_chip_selects: Mapping[int, tuple[int, ...]]
    i2c_clock_hz: Mapping[int, int]
    reserved: Mapping[int, str]
    source: str
    boards: tuple[str, ...] = ()
    lacks: str = ""

    @property
    def i2c_buses(self) -> tuple[int, ...]:
        return tuple(self.i2c_clock_hz)


_BCM283X_SPI = MappingProxyType({
    0: SPIController(0, "spi-bcm2835", frozenset({0, 1, 2, 3}), (9, 10, 11)),
    1: SPIController(1, "spi-bcm2835aux (the auxiliary SPI: CPHA = 0 only)", frozenset({0, 2}), (19, 20, 21)),
})
_RP1_SPI = MappingProxyType({bus: SPIController(bus, "dw-apb-ssi on RP1", frozenset({0, 1, 2, 3}), None)
                             for bus in (0, 1)})


def _board(name, model, compatible, controller, mainline, raspberrypi, spi, i2c_pins) -> HostBoard:
    return HostBoard(name, model, compatible, controller,
                     MappingProxyType({"mainline": mainline, "raspberrypi": raspberrypi}), spi,
                     MappingProxyType({1: i2c_pins}))


HOST_BOARDS = MappingProxyType({board.name: board for board in (
    _board("pi3b", "Raspberry Pi 3 Model B", "raspberrypi,3-model-b", "&gpio (gpio@7e200000)",
           _MAINLINE_BCM283X, _MAINLINE_BCM283X, _BCM283X_SPI, (2, 3)),
    _board("pi3b-plus", "Raspberry Pi 3 Model B+", "raspberrypi,3-model-b-plus", "&gpio (gpio@7e200000)",
           _MAINLINE_BCM283X, _GPIO_NUMBERED, _BCM283X_SPI, (2, 3)),
    _board("pi4b", "Raspberry Pi 4 Model B", "raspberrypi,4-model-b", "&gpio (gpio@7e200000)",
           _MAINLINE_BCM283X, _GPIO_NUMBERED, _BCM283X_SPI, (2, 3)),
    _board("pi5", "Raspberry Pi 5", "raspberrypi,5-model-b", "&rp1_gpio (on RP1)",
           None, _GPIO_NUMBERED, _RP1_SPI, None),
    _board("generic", "an unknown board with a Raspberry Pi header", None, "unknown",
           None, None, MappingProxyType({}), None),
)})
"""The boards by the name ``--board`` takes; ``generic`` checks only what holds for any board."""

I2C_DEFAULT_CLOCK_HZ = 100_000
"""The I2C clock a bus runs at when its device tree sets none (and the one the mainline Pi trees set)."""
_FAST_I2C = MappingProxyType({1: 400_000})
_PI_OS_SOURCE = ("config.txt dtparam=spi=on, dtparam=i2c_arm=on, dtparam=i2c_arm_baudrate=400000 and "
                 "dtoverlay={overlay} (raspberrypi/linux arch/arm/boot/dts/overlays/{overlay}-overlay.dts)")
_IMAGE_SOURCE = ("image-build/files/appliance-buses.dts and appliance-spi1-{n}cs.dts, applied by "
                 "image-build/device-trees.sh at build time to the mainline trees of Debian's kernel: SPI0 with CE0 "
                 "and CE1, SPI1 with {n} chip select(s) on GPIO {pins}, I2C1 at 400 kHz; image-build/files/"
                 "raspi-firmware (console ttyS1)")
_IMAGE_CONSOLE = MappingProxyType({14: "UART1 TXD (the serial console, ttyS1)", 15: "UART1 RXD (the serial console)"})
_PI3_PI4 = ("pi3b", "pi3b-plus", "pi4b")
SYSTEMS = MappingProxyType({system.name: system for system in (
    System("appliance-image", "mainline", MappingProxyType({0: (8, 7), 1: (18,)}), _FAST_I2C, _IMAGE_CONSOLE,
           _IMAGE_SOURCE.format(n=1, pins="18"), _PI3_PI4),
    System("appliance-image-spi1-3cs", "mainline", MappingProxyType({0: (8, 7), 1: (18, 17, 16)}), _FAST_I2C,
           _IMAGE_CONSOLE, _IMAGE_SOURCE.format(n=3, pins="18, 17 and 16"), _PI3_PI4),
    System("appliance-image-pi5", "mainline", MappingProxyType({}), MappingProxyType({}), MappingProxyType({}),
           "image-build/build-image.sh --board pi5: Debian trixie with linux-image-arm64 from trixie-backports and "
           "raspi-firmware; no bus is enabled", ("pi5",),
           "Debian's only kernel with RP1's drivers (7.3, trixie-backports) has no driver for RP1's SPI "
           "controllers (CONFIG_SPI_DESIGNWARE is not set), and the image enables none of RP1's I2C "
           "controllers (their pin groups were not verified)"),
    System("raspberry-pi-os-spi1-1cs", "raspberrypi", MappingProxyType({0: (8, 7), 1: (18,)}), _FAST_I2C,
           MappingProxyType({}), _PI_OS_SOURCE.format(overlay="spi1-1cs")),
    System("raspberry-pi-os-spi1-3cs", "raspberrypi", MappingProxyType({0: (8, 7), 1: (18, 17, 16)}), _FAST_I2C,
           MappingProxyType({}), _PI_OS_SOURCE.format(overlay="spi1-3cs")),
)})
"""The systems a profile may name as ``system``; ``appliance-image*`` are what image-build/ makes (the variant
by ``build-image.sh --profile``, the Pi 5's by ``--board pi5``)."""
DEFAULT_SYSTEM = "appliance-image"


def host_of_compatible(compatible: str) -> HostBoard:
    """The board whose device tree ``compatible`` is this (the first entry of /proc/device-tree/compatible)."""
    for board in HOST_BOARDS.values():
        if board.compatible == compatible:
            return board
    return HOST_BOARDS["generic"]
