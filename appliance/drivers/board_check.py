"""Hold a board profile against the host board and system it runs on, before any bus is opened.

On a Pi each of these mistakes shows only as a bare errno from one device, or not at all (two users of
one pin): a line the kernel names otherwise, a pin used twice, a pin an enabled bus has claimed, an SPI
mode the controller refuses, a bus the system does not enable or runs too slowly for the profile's timing, a
system built for another board. :func:`check_profile` reports all of them
at once, each naming the role, the pin and the device. It runs where the Linux board is opened and in
``appliance selftest --check``.

>>> from appliance.drivers.profile import board_profile
>>> check_profile(board_profile({"profile": "reference"}), HOST_BOARDS["pi4b"])
"""

from __future__ import annotations

import re
from pathlib import Path

from appliance.drivers.ad7606 import AD7606Array
from appliance.drivers.ad9833 import AD9833
from appliance.drivers.adg7xx import ADG725, ADG731
from appliance.drivers.adg1414 import ADG1414Chain
from appliance.drivers.boards import HEADER_GPIOS, HOST_BOARDS, SYSTEMS, HostBoard, System, host_of_compatible
from appliance.drivers.profile import MULTIPLEXERS, BoardProfile
from appliance.errors import BoardMismatch

CHIP_BY_SPI_ROLE: dict[str, type[AD9833 | AD7606Array | ADG1414Chain | ADG725 | ADG731]] = {
    "dds": AD9833, "adc": AD7606Array, "drive_switches": ADG1414Chain,
    **dict.fromkeys(MULTIPLEXERS["adg725"], ADG725), **dict.fromkeys(MULTIPLEXERS["adg731"], ADG731)}
"""The chip driver behind each SPI role, whose ``SPI_MODE`` is the mode the device is opened in."""
DEVICE_TREE_COMPATIBLE = Path("/proc/device-tree/compatible")


def running_host(compatible_file: Path = DEVICE_TREE_COMPATIBLE) -> HostBoard:
    """The board this computer is, from its device tree's first ``compatible``; ``generic`` if unknown."""
    try:
        compatible = compatible_file.read_bytes().split(b"\0")[0].decode("ascii", "replace")
    except OSError:
        return HOST_BOARDS["generic"]
    return host_of_compatible(compatible)


def check_profile(profile: BoardProfile, host: HostBoard, system: System | None = None) -> None:
    """Raise :class:`~appliance.errors.BoardMismatch` listing every way ``profile`` does not fit ``host``.

    ``system`` defaults to the one the profile names.
    """
    system = system or SYSTEMS[profile.system]
    problems: list[str] = []
    if system.boards and host.name != "generic" and host.name not in system.boards:
        problems.append(f"{system.name} is built for {', '.join(system.boards)}, not {host.name}")
    used: dict[int, str] = {}
    for role, address in profile.spi.items():
        problems += _spi_problems(role, address, host, system, used)
    problems += _i2c_problems(profile, system)
    claimed = _claimed_pins(host, system)
    names = host.names(system.kernel)
    for role, line in profile.gpio.items():
        where = f"[board.gpio] {role} = {line!r}"
        pin, problem = _header_pin(line, names, host, system)
        if problem:
            problems.append(f"{where}: {problem}")
        elif pin in used:
            problems.append(f"{where}: GPIO {pin} is already {used[pin]}")
        elif pin in claimed:
            problems.append(f"{where}: GPIO {pin} is {claimed[pin]}, which {system.name} enables, so the kernel "
                            "holds the pin")
        else:
            used[pin] = f"[board.gpio] {role}"
    if problems:
        raise BoardMismatch(f"profile {profile.name} does not fit {host.name} ({host.model}) running {system.name}:\n"
                            + "\n".join(f"  {problem}" for problem in problems))


def _spi_problems(role: str, address, host: HostBoard, system: System, used: dict[int, str]) -> list[str]:
    bus, chip_select = address.bus, address.chip_select
    device = f"/dev/spidev{bus}.{chip_select} ({role})"
    problems = []
    chip_selects = system.spi_chip_selects.get(bus)
    if chip_selects is None:
        problems.append(f"{device}: {system.name} does not enable SPI{bus}{_why(system)}")
    elif chip_select >= len(chip_selects):
        problems.append(f"{device}: {system.name} enables only {len(chip_selects)} chip select(s) on SPI{bus}")
    else:
        used[chip_selects[chip_select]] = f"SPI{bus} CE{chip_select} ({role})"
    chip = CHIP_BY_SPI_ROLE[role]
    controller = host.spi.get(bus)
    if controller is not None and controller.modes is not None and chip.SPI_MODE not in controller.modes:
        problems.append(f"{device}: the {chip.__name__} is opened in SPI mode {chip.SPI_MODE}, but SPI{bus} "
                        f"({controller.driver}) takes only modes {sorted(controller.modes)}: "
                        "the kernel would answer EINVAL")
    return problems


def _i2c_problems(profile: BoardProfile, system: System) -> list[str]:
    bus = profile.i2c_bus
    clock = system.i2c_clock_hz.get(bus)
    if clock is None:
        return [f"I2C{bus} ([board.i2c] bus): {system.name} does not enable it (it enables I2C "
                f"{', '.join(map(str, system.i2c_buses)) or 'none'}){_why(system)}"]
    if clock < profile.timing.i2c_clock_hz:
        return [f"I2C{bus} runs at {clock / 1e3:g} kHz under {system.name}, but the profile's timing needs "
                f"{profile.timing.i2c_clock_hz / 1e3:g} kHz ([board.timing] i2c_clock_hz)"]
    return []


def _why(system: System) -> str:
    return f" ({system.name} lacks buses: {system.lacks})" if system.lacks else ""


def _claimed_pins(host: HostBoard, system: System) -> dict[int, str]:
    """{GPIO: what holds it} for every pin a bus or service the system enables takes from GPIO users."""
    claimed = dict(system.reserved)
    for bus, chip_selects in system.spi_chip_selects.items():
        claimed.update({pin: f"SPI{bus} CE{k}" for k, pin in enumerate(chip_selects)})
        controller = host.spi.get(bus)
        if controller is not None and controller.data_pins is not None:
            claimed.update(zip(controller.data_pins, (f"SPI{bus} {signal}" for signal in ("MISO", "MOSI", "SCLK"))))
    for bus in system.i2c_buses:
        pins = host.i2c_pins.get(bus)
        if pins is not None:
            claimed.update(zip(pins, (f"I2C{bus} SDA", f"I2C{bus} SCL")))
    return claimed


def _header_pin(line: str, names: tuple[str, ...] | None, host: HostBoard, system: System) -> tuple[int, str]:
    """(GPIO number, "") for a line the host has under the system's kernel, else (-1, why it has none)."""
    numbered = re.fullmatch(r"GPIO(\d+)", line)
    number = int(numbered[1]) if numbered and int(numbered[1]) < HEADER_GPIOS else None
    if names is None:
        if number is None:
            return -1, (f"the line names of {host.name} under the {system.kernel} kernel are not verified, so only "
                        f"header pins named GPIO0..GPIO{HEADER_GPIOS - 1} can be checked")
        return number, ""
    if line in names:
        return names.index(line), ""
    hint = (f"; GPIO {number} is named {names[number]!r} there" if number is not None
            else f"; its header lines are {', '.join(names)}")
    return -1, f"{host.name} has no line of that name under the {system.kernel} kernel{hint}"
