"""Wiring tables for the person who builds or checks a front end: every chip's signal to its header pin.

Made from the profile (roles, buses, chip selects, lines) and the host-board facts (``drivers/boards.py``:
the SPI and I2C pins, the line names each board's kernel gives), so the tables in ``docs/bring-up.md`` are
what the code will open, and ``appliance wiring`` prints them for any ``[board]`` table. A second table
gives the analogue parts' rails (``drivers/rails.py``), which a meter checks before the first self-test.

>>> from appliance.drivers.profile import board_profile
>>> rows = wiring_rows(board_profile({"profile": "reference"}))
>>> [row for row in rows if row[0] == "AD8251 in-amp"][0][:5]
('AD8251 in-amp', 'A0', 'GPIO', 5, 29)
"""

from __future__ import annotations

import math

from appliance.drivers.boards import HOST_BOARDS, SYSTEMS
from appliance.drivers.profile import BoardProfile
from appliance.drivers.rails import AMPLIFIER_PART, RATINGS, multiplexer_peak_v
from appliance.errors import ConfigError

HEADER_PIN = {2: 3, 3: 5, 4: 7, 14: 8, 15: 10, 17: 11, 18: 12, 27: 13, 22: 15, 23: 16, 24: 18, 10: 19, 9: 21,
              25: 22, 11: 23, 8: 24, 7: 26, 0: 27, 1: 28, 5: 29, 6: 31, 12: 32, 13: 33, 19: 35, 16: 36, 26: 37,
              20: 38, 21: 40}
"""BCM GPIO number -> pin of the 40-pin header, the same on every board here (Raspberry Pi documentation,
"GPIO and the 40-pin header")."""

SPI_CHIPS = {"dds": ("AD9833 sine source", ("SCLK", "MOSI")),
             "adc": ("AD7606 converters (by way of the 74HC154 decoders' enable)", ("SCLK", "MISO")),
             "drive_switches": ("ADG1414 drive switch chain", ("SCLK", "MOSI", "MISO")),
             "drive_mux": ("ADG725 drive multiplexer", ("SCLK", "MOSI")),
             "measure_mux": ("ADG725 measuring multiplexer", ("SCLK", "MOSI")),
             "drive_pos_mux": ("ADG731 drive+ multiplexer", ("SCLK", "MOSI")),
             "drive_neg_mux": ("ADG731 drive- multiplexer", ("SCLK", "MOSI")),
             "meas_pos_mux": ("ADG731 measure+ multiplexer", ("SCLK", "MOSI")),
             "meas_neg_mux": ("ADG731 measure- multiplexer", ("SCLK", "MOSI"))}
"""Each SPI role's chip and the data lines it uses (MISO only where the chip answers)."""
I2C_CHIPS = {"adc": "ADS1115 converter", "digipot": "MCP4017 digipot", "thermometer": "MCP9808 thermometer",
             "impedance": "AD5933 impedance converter"}
GPIO_SIGNALS = {"gain_a0": ("AD8251 in-amp", "A0"), "gain_a1": ("AD8251 in-amp", "A1"),
                "gain_wr": ("AD8251 in-amp", "/WR"), "adc_ready": ("ADS1115 converter", "ALERT/RDY (open drain)"),
                "phase_sign": ("phase comparator", "output"), "source_enable": ("current source", "enable"),
                "buzzer": ("buzzer", "drive"), "status_led": ("status LED", "drive"),
                "adc_convst": ("AD7606 converters", "CONVST A and B"), "adc_busy": ("AD7606 converters", "BUSY"),
                "adc_reset": ("AD7606 converters", "RESET"), "adc_range": ("AD7606 converters", "RANGE")}
"""Each GPIO role's chip and signal; ``adc_cs_aN`` are the decoder's address lines."""
DATA_SIGNALS = ("MISO", "MOSI", "SCLK")


def _gpio_signal(role: str) -> tuple[str, str]:
    if role.startswith("adc_cs_a"):
        return "74HC154 / 74HC139 decoders", f"address A{role.removeprefix('adc_cs_a')}"
    return GPIO_SIGNALS.get(role, (role.replace("_", " "), "line"))


def wiring_rows(profile: BoardProfile) -> list[tuple]:
    """(chip, signal, bus, BCM GPIO, header pin, line name on each of the profile's boards) for every wire."""
    system = SYSTEMS[profile.system]
    host = HOST_BOARDS[profile.boards[0]] if profile.boards else HOST_BOARDS["pi4b"]
    boards = [HOST_BOARDS[name] for name in profile.boards] or [host]

    def row(chip, signal, bus, bcm):
        names = tuple((board.names(system.kernel) or ())[bcm] if board.names(system.kernel) else "not verified"
                      for board in boards)
        return (chip, signal, bus, bcm, HEADER_PIN[bcm], *names)

    rows = []
    for bus in sorted({address.bus for address in profile.spi.values()}):
        controller = host.spi[bus]
        if controller.data_pins is None:
            raise ConfigError(f"the {host.model}'s SPI{bus} pins are not known: the wiring table cannot list them")
        roles = [role for role, address in profile.spi.items() if address.bus == bus]
        used = {signal for role in roles for signal in SPI_CHIPS[role][1]}
        for signal, bcm in zip(DATA_SIGNALS, controller.data_pins):
            if signal in used:
                rows.append(row(f"SPI{bus} bus", signal, f"SPI{bus}", bcm))
        for role in sorted(roles, key=lambda r: profile.spi[r].chip_select):
            address = profile.spi[role]
            rows.append(row(SPI_CHIPS[role][0], "/SYNC or /CS", f"SPI{bus} CE{address.chip_select}",
                            system.spi_chip_selects[bus][address.chip_select]))
    i2c_pins = host.i2c_pins.get(profile.i2c_bus)
    if i2c_pins is None:
        raise ConfigError(f"the {host.model}'s I2C{profile.i2c_bus} pins are not known: the wiring table cannot "
                          "list them")
    sda, scl = i2c_pins
    rows.append(row(f"I2C{profile.i2c_bus} bus", "SDA", f"I2C{profile.i2c_bus}", sda))
    rows.append(row(f"I2C{profile.i2c_bus} bus", "SCL", f"I2C{profile.i2c_bus}", scl))
    for role, i2c_address in profile.i2c.items():
        rows.append((I2C_CHIPS.get(role, role), f"address 0x{i2c_address:02X}", f"I2C{profile.i2c_bus}", "", "",
                     *("" for _ in boards)))
    for role, line in profile.gpio.items():
        bcm = _bcm_of(line, host, system)
        chip, signal = _gpio_signal(role)
        rows.append(row(chip, signal, "GPIO", bcm))
    return rows


def _bcm_of(line: str, host, system) -> int:
    names = host.names(system.kernel)
    if names and line in names:
        return names.index(line)
    return int(line.removeprefix("GPIO"))


def supply_rows(profile: BoardProfile) -> list[tuple[str, str, str]]:
    """(parts, rails, what they must be) for each analogue supply, and the compliance they give."""
    s = profile.supply
    mux = RATINGS[profile.multiplexer]
    rows = [(f"{mux.part} {mux.role}", _rails(s.multiplexers),
             f"VDD - VSS {mux.span_v[0]:g} to {mux.span_v[1]:g} V; pass {multiplexer_peak_v(profile):g} V peak")]
    amplifier = AMPLIFIER_PART[profile.chain]
    rows.append(("in-amps" + (f", {RATINGS[amplifier].part}" if amplifier else ""), _rails(s.amplifiers),
                 f"VDD - VSS {RATINGS[amplifier].span_v[0]:g} to {RATINGS[amplifier].span_v[1]:g} V"
                 if amplifier else "as the in-amps' data sheet"))
    compliance = profile.excitation.compliance_v
    assert compliance is not None           # board_profile sets it, from the rails if the profile does not
    rows.append(("current source", _rails(s.current_source),
                 f"compliance {compliance:.2f} V rms ({compliance * math.sqrt(2):.2f} V peak), "
                 f"{s.source_headroom_v:g} V short of its rails"))
    return rows


def _rails(rails) -> str:
    return f"{rails[0]:+g} V / {rails[1]:+g} V"


def wiring_markdown(profile: BoardProfile) -> str:
    """The profile's wiring and supply tables, as markdown."""
    system = SYSTEMS[profile.system]
    boards = list(profile.boards) or ["pi4b"]
    header = ["chip", "signal", "bus", "BCM GPIO", "header pin", *(f"line on {b}" for b in boards)]
    lines = [f"### {profile.name}", "",
             f"System `{profile.system}` ({system.kernel} kernel); host boards {', '.join(boards)}; detector "
             f"`{profile.measurement.detector}`.", "",
             "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in wiring_rows(profile)]
    lines += ["", "| analogue parts | rails | must be |", "|---|---|---|"]
    lines += ["| " + " | ".join(row) + " |" for row in supply_rows(profile)]
    return "\n".join(lines) + "\n"
