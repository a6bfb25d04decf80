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

    ``spi_chip_selects`` maps each enabled SPI bus to the GPIO of each chip select (CE0 first); ``reserved``
    names other header pins the system takes for itself.
    """

    name: str
    kernel: str
    spi_chip_selects: Mapping[int, tuple[int, ...]]
    i2c_buses: tuple[int, ...]
    reserved: Mapping[int, str]
    source: str


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

_PI_OS_SOURCE = ("config.txt dtparam=spi=on, dtparam=i2c_arm=on and dtoverlay={overlay} (raspberrypi/linux "
                 "arch/arm/boot/dts/overlays/{overlay}-overlay.dts)")
SYSTEMS = MappingProxyType({system.name: system for system in (
    System("appliance-image", "mainline", MappingProxyType({0: (8, 7)}), (1,),
           MappingProxyType({14: "UART1 TXD (the serial console, ttyS1)", 15: "UART1 RXD (the serial console)"}),
           "image-build/files/appliance-spi.dts (SPI0 with CE0 and CE1, I2C1) on Debian's kernel and mainline "
           "trees, which ignore config.txt's dtparam lines; image-build/files/raspi-firmware (console ttyS1)"),
    System("raspberry-pi-os-spi1-1cs", "raspberrypi", MappingProxyType({0: (8, 7), 1: (18,)}), (1,),
           MappingProxyType({}), _PI_OS_SOURCE.format(overlay="spi1-1cs")),
    System("raspberry-pi-os-spi1-3cs", "raspberrypi", MappingProxyType({0: (8, 7), 1: (18, 17, 16)}), (1,),
           MappingProxyType({}), _PI_OS_SOURCE.format(overlay="spi1-3cs")),
)})
"""The systems a profile may name as ``system``; ``appliance-image`` is what image-build/ makes."""
DEFAULT_SYSTEM = "appliance-image"


def host_of_compatible(compatible: str) -> HostBoard:
    """The board whose device tree ``compatible`` is this (the first entry of /proc/device-tree/compatible)."""
    for board in HOST_BOARDS.values():
        if board.compatible == compatible:
            return board
    return HOST_BOARDS["generic"]
