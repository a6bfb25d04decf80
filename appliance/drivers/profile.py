"""Board profiles: which chips the front end has, where they sit, and how long they take.

A profile is the ``[board]`` section of the appliance's TOML configuration. It
names a built-in profile (``reference``, ``reference-32``, ``ad5933``, ``parallel``;
files in ``drivers/profiles/``) and may override any of its keys, so a board that
moved a chip select or settles more slowly needs two lines, not a copy. GPIO lines are
named as the kernel of the profile's ``system`` names them ("GPIO17"; "GPIO_GCLK" for
GPIO 4 under the mainline device trees), never as a GPIO chip and offset; ``boards``
lists the host boards it is wired for (``drivers/board_check.py`` holds it against
them). ``[supply]`` gives the analogue parts' rails, from which ``drivers/rails.py``
derives the current source's compliance (a profile whose parts do not fit their rails
is refused); ``[measurement] detector``, if given, must be what the chain's detector is.
The parallel front end is built for a grid of electrodes given in its ``[grid]``
table, so the same profile describes the bed mat and a small test mat
(``grid = {rows = 4, cols = 8}``).

>>> profile = board_profile({"profile": "reference", "gpio": {"buzzer": "GPIO21"}})
>>> profile.gpio["buzzer"], profile.spi["dds"].chip_select, profile.timing.drive_settle_s
('GPIO21', 0, 0.0005)
"""

from __future__ import annotations

import dataclasses
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from importlib import resources
from types import MappingProxyType
from typing import Any

from appliance.core.toml_files import check_keys, read_toml
from appliance.drivers.boards import DEFAULT_SYSTEM, HOST_BOARDS, SYSTEMS
from appliance.errors import ConfigError

BUILTIN_PROFILES = ("reference", "reference-32", "ad5933", "parallel")
CHAINS = ("rms", "ad5933", "parallel")
MULTIPLEXERS = {"adg725": ("drive_mux", "measure_mux"),
                "adg731": ("drive_pos_mux", "drive_neg_mux", "meas_pos_mux", "meas_neg_mux"),
                "adg1414": ("drive_switches",)}
MULTIPLEXER_CHANNELS = {"adg725": 16, "adg731": 32}
"""Electrodes a multiplexer set reaches; the ADG1414 switch matrix reaches the profile's whole grid."""
ADC_OVERSAMPLING = (1, 2, 4, 8, 16, 32, 64)
"""The AD7606's oversampling ratios, set by its OS[2:0] pins (strapped on the board)."""
ADC_ADDRESS_LINE = "adc_cs_a"
ROLES_BY_CHAIN = {
    "rms": {"spi": ("dds",), "i2c": ("adc", "digipot", "thermometer"),
            "gpio": ("gain_a0", "gain_a1", "gain_wr", "adc_ready", "phase_sign", "source_enable")},
    "ad5933": {"spi": (), "i2c": ("impedance", "thermometer"),
               "gpio": ("gain_a0", "gain_a1", "gain_wr", "source_enable")},
    "parallel": {"spi": ("dds", "adc"), "i2c": ("digipot", "thermometer"),
                 "gpio": ("adc_convst", "adc_busy", "adc_reset", "adc_range", f"{ADC_ADDRESS_LINE}0",
                          "source_enable")},
}
FIELDS_BY_CHAIN = {
    "rms": {"excitation": ("current_a", "full_scale_current_a"),
            "measurement": ("rms_limit_v", "adc_data_rate_sps"),
            "contact": ("test_current_a",),
            "timing": ("measure_settle_s", "rms_rise_tau_s", "rms_fall_tau_s", "settle_accuracy")},
    "ad5933": {"excitation": ("output_range_vpp", "transconductance_a_per_v"),
               "measurement": ("vin_gain", "settling_cycles", "dft_counts_per_volt"),
               "timing": ("measure_settle_s",)},
    "parallel": {"excitation": ("current_a", "full_scale_current_a"),
                 "measurement": ("lowpass_gain", "lowpass_hz", "adc_oversampling", "channels_per_adc",
                                 "adc_tile_rows"),
                 "contact": ("test_current_a",)},
}


DETECTORS = {"rms": "rms", "ad5933": "dft", "parallel": "synchronous"}
"""What each chain's detector reports: ``rms`` the magnitude (an AD8436: the quadrature from contact capacitance
included, the sign from a phase comparator), ``dft`` the real and imaginary parts (the AD5933), ``synchronous``
the in-phase part alone (a demodulator switched by the excitation). ``dft`` and ``synchronous`` are phase-sensitive."""
PHASE_SENSITIVE = ("dft", "synchronous")


@dataclass(frozen=True)
class Excitation:
    frequency_hz: float
    compliance_v: float | None = None          # rms; the current source's clamp, else what its rails allow
    current_a: float | None = None
    full_scale_current_a: float | None = None
    output_range_vpp: float | None = None
    transconductance_a_per_v: float | None = None


@dataclass(frozen=True)
class Measurement:
    inamp_gain: float
    range_headroom: float
    sign_floor_v: float
    rms_limit_v: float | None = None
    adc_data_rate_sps: int | None = None
    vin_gain: float | None = None
    settling_cycles: int | None = None
    dft_counts_per_volt: float | None = None
    lowpass_gain: float | None = None          # parallel chain: gain of the low-pass after the demodulator
    lowpass_hz: float | None = None            # its -3 dB frequency (two equal real poles)
    adc_oversampling: int | None = None        # AD7606 OS[2:0] strap
    channels_per_adc: int | None = None
    adc_tile_rows: int | None = None           # grid rows one ADC's channels span
    detector: str | None = None                # what the chain's detector reports: one of DETECTORS' values
    input_capacitance_f: float | None = None   # each measuring input to ground: multiplexer, cable, in-amp


@dataclass(frozen=True)
class Supply:
    """The analogue parts' rails, volts (negative, positive), and how close the source's output comes to its own."""

    multiplexers: tuple[float, float]
    current_source: tuple[float, float]
    amplifiers: tuple[float, float]
    source_headroom_v: float


@dataclass(frozen=True)
class Accuracy:
    """The stated error of one reading against the sensor: ``relative * |v| + absolute_v``."""

    relative: float
    absolute_v: float


@dataclass(frozen=True)
class Contact:
    limit_ohm: float
    test_current_a: float | None = None
    every_frames: int | None = None            # check contacts every this many frames (default every frame)


@dataclass(frozen=True)
class Timing:
    drive_settle_s: float
    i2c_clock_hz: float                        # the I2C clock the timing is designed for: the system must give it
    call_overhead_s: float
    measure_settle_s: float | None = None
    rms_rise_tau_s: float | None = None
    rms_fall_tau_s: float | None = None
    settle_accuracy: float | None = None


@dataclass(frozen=True)
class SPIAddress:
    bus: int
    chip_select: int
    max_speed_hz: int


@dataclass(frozen=True)
class Grid:
    """The electrode grid a parallel front end is built for: rows x cols, numbered row-major from 1."""

    rows: int
    cols: int


@dataclass(frozen=True)
class BoardProfile:
    """A whole board: chips, bus addresses, pins, analogue constants and timing."""

    name: str
    chain: str
    multiplexer: str
    channels: int
    excitation: Excitation
    measurement: Measurement
    accuracy: Accuracy
    contact: Contact
    timing: Timing
    supply: Supply
    spi: Mapping[str, SPIAddress]
    i2c_bus: int
    i2c: Mapping[str, int]
    gpio: Mapping[str, str] = field(default_factory=dict)
    grid: Grid | None = None
    system: str = DEFAULT_SYSTEM
    boards: tuple[str, ...] = ()
    """The host boards (``drivers/boards.py``) this profile is wired for and checked against."""

    @property
    def device_nodes(self) -> tuple[str, ...]:
        """The device files the Linux board opens for this profile: a spidev node per SPI chip select and the I2C
        adapter (GPIO lines are found by name, on whichever ``/dev/gpiochip*`` carries them)."""
        spi = sorted({f"/dev/spidev{address.bus}.{address.chip_select}" for address in self.spi.values()})
        return (*spi, f"/dev/i2c-{self.i2c_bus}")

    @property
    def adc_address_lines(self) -> tuple[str, ...]:
        """The header lines of the ADC chip-select decoder's address, least significant first."""
        lines: list[str] = []
        while f"{ADC_ADDRESS_LINE}{len(lines)}" in self.gpio:
            lines.append(self.gpio[f"{ADC_ADDRESS_LINE}{len(lines)}"])
        return tuple(lines)


def builtin_profile_text(name: str) -> str:
    """The TOML text of a built-in profile."""
    if name not in BUILTIN_PROFILES:
        raise ConfigError(f"[board] profile {name!r} is not built in; the built-in profiles are "
                          f"{', '.join(BUILTIN_PROFILES)}")
    return resources.files("appliance.drivers").joinpath(f"profiles/{name}.toml").read_text(encoding="utf-8")


def board_profile(board: Mapping[str, Any] | None = None) -> BoardProfile:
    """The profile a ``[board]`` table describes: its built-in ``profile`` with the table's overrides.

    Keys that are not the appliance's (``backend``, ``gpio_chip``) are ignored here;
    any other unknown key is an error naming it, so a typo cannot silently keep a default.
    """
    board = dict(board or {})
    name = board.pop("profile", "reference")
    for key in ("backend", "gpio_chip"):
        board.pop(key, None)
    data = _merge(tomllib.loads(builtin_profile_text(name)), board)
    return _profile_from_mapping(data)


def _merge(base: dict, overrides: Mapping) -> dict:
    merged = dict(base)
    for key, value in overrides.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), dict):
            merged[key] = _merge(merged[key], value)
        else:
            merged[key] = value
    return merged


def _profile_from_mapping(data: dict) -> BoardProfile:
    data = dict(data)
    name = _take(data, "name", str, "[board]")
    where = f"[board] (profile {name})"
    chain = _take(data, "chain", str, where)
    if chain not in CHAINS:
        raise ConfigError(f"{where} chain must be one of {CHAINS}, got {chain!r}")
    multiplexer = _take(data, "multiplexer", str, where)
    if multiplexer not in MULTIPLEXERS:
        raise ConfigError(f"{where} multiplexer must be one of {tuple(MULTIPLEXERS)}, got {multiplexer!r}")
    if (multiplexer == "adg1414") != (chain == "parallel"):
        raise ConfigError(f"{where}: the {chain} chain cannot use the {multiplexer}")
    grid = _grid(data, where) if chain == "parallel" else None
    if "grid" in data:
        raise ConfigError(f"{where}: [board.grid] belongs to a parallel front end, not a {chain} one")
    expected = grid.rows * grid.cols if grid else MULTIPLEXER_CHANNELS[multiplexer]
    channels = _take(data, "channels", int, where) if grid is None or "channels" in data else expected
    if channels != expected:
        raise ConfigError(f"{where} channels = {channels} does not match the {multiplexer}"
                          + (f" on a {grid.rows} x {grid.cols} grid ({expected} electrodes)" if grid else ""))
    sections = {key: _section(cls, _take(data, key, dict, where), f"[board.{key}]")
                for key, cls in (("excitation", Excitation), ("measurement", Measurement),
                                 ("accuracy", Accuracy), ("contact", Contact), ("timing", Timing))}
    supply = _supply(_take(data, "supply", dict, where))
    spi = {role: _section(SPIAddress, value, f"[board.spi] {role}")
           for role, value in _take(data, "spi", dict, where).items()}
    i2c = dict(_take(data, "i2c", dict, where))
    i2c_bus = _take(i2c, "bus", int, "[board.i2c]")
    gpio = _take(data, "gpio", dict, where) if "gpio" in data else {}
    system = _take(data, "system", str, where) if "system" in data else DEFAULT_SYSTEM
    if system not in SYSTEMS:
        raise ConfigError(f"{where} system must be one of {tuple(SYSTEMS)}, got {system!r}")
    boards = tuple(_take(data, "boards", list, where)) if "boards" in data else ()
    unknown = [board for board in boards if board not in HOST_BOARDS]
    if unknown:
        raise ConfigError(f"{where} boards: {unknown[0]!r} is not one of {tuple(HOST_BOARDS)}")
    check_keys(data, (), where, ConfigError)
    roles = ROLES_BY_CHAIN[chain]
    _require(spi, roles["spi"] + MULTIPLEXERS[multiplexer], "[board.spi]")
    _require(i2c, roles["i2c"], "[board.i2c]")
    _require(gpio, roles["gpio"], "[board.gpio]")
    for role, address in i2c.items():
        if not (isinstance(address, int) and 0x03 <= address <= 0x77):
            raise ConfigError(f"[board.i2c] {role} = {address!r} is not a 7-bit I2C address (0x03..0x77)")
    for role, line in gpio.items():
        if not isinstance(line, str) or not line:
            raise ConfigError(f"[board.gpio] {role} must be a line name such as \"GPIO17\", got {line!r}")
    _check_distinct(spi, "[board.spi]", lambda a: f"spi{a.bus}.{a.chip_select}")
    _check_distinct(gpio, "[board.gpio]", lambda line: line)
    _check_distinct(i2c, "[board.i2c]", lambda address: f"0x{address:02X}")
    if sections["contact"].every_frames is not None and sections["contact"].every_frames < 1:
        raise ConfigError(f"[board.contact] every_frames must be at least 1, got {sections['contact'].every_frames}")
    for key, names in FIELDS_BY_CHAIN[chain].items():
        missing = [n for n in names if getattr(sections[key], n) is None]
        if missing:
            raise ConfigError(f"[board.{key}] needs {missing[0]!r} for a {chain} front end")
    excitation, measurement = _analogue(name, chain, multiplexer, supply, sections, "dds" in spi)
    profile = BoardProfile(name=name, chain=chain, multiplexer=multiplexer, channels=channels,
                           excitation=excitation, measurement=measurement,
                           accuracy=sections["accuracy"], contact=sections["contact"], timing=sections["timing"],
                           supply=supply, spi=MappingProxyType(spi), i2c_bus=i2c_bus, i2c=MappingProxyType(i2c),
                           gpio=MappingProxyType(gpio), grid=grid, system=system, boards=boards)
    if chain == "parallel":
        _check_parallel(profile, where)
    return profile


def _supply(values: Mapping) -> Supply:
    values, where = dict(values), "[board.supply]"
    rails = {}
    for key in ("multiplexers", "current_source", "amplifiers"):
        pair = _take(values, key, list, where)
        if len(pair) != 2 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in pair):
            raise ConfigError(f"{where} {key} must be two numbers, the negative and the positive rail in volts, "
                              f"got {pair!r}")
        rails[key] = (float(pair[0]), float(pair[1]))
    headroom = _take(values, "source_headroom_v", float, where)
    if headroom < 0:
        raise ConfigError(f"{where} source_headroom_v must not be negative, got {headroom!r}")
    check_keys(values, (), where, ConfigError)
    return Supply(**rails, source_headroom_v=headroom)


def _analogue(name: str, chain: str, multiplexer: str, supply: Supply, sections: dict, uses_dds: bool):
    """The excitation with the compliance its rails give, and the measurement with its chain's detector."""
    from appliance.drivers.rails import check_supplies
    from appliance.errors import AnalogueMismatch

    excitation, measurement = sections["excitation"], sections["measurement"]
    own = DETECTORS[chain]
    if measurement.detector not in (None, own):
        claimed = measurement.detector
        why = (f"the {chain} chain's detector reports {own!r}"
               + (": the AD8436 RMS-to-DC converter gives the magnitude, quadrature from contact capacitance "
                  "included, so it is not phase-sensitive" if own == "rms" and claimed in PHASE_SENSITIVE else ""))
        raise AnalogueMismatch(f"profile {name}: [board.measurement] detector = {claimed!r}, but {why}")
    compliance = check_supplies(name, multiplexer, chain, supply, excitation.compliance_v, uses_dds)
    return (dataclasses.replace(excitation, compliance_v=compliance),
            dataclasses.replace(measurement, detector=own))


def _grid(data: dict, where: str) -> Grid:
    grid = _section(Grid, _take(data, "grid", dict, where), "[board.grid]")
    if grid.rows < 1 or grid.cols < 2:
        raise ConfigError(f"[board.grid] needs at least 1 row and 2 columns (a pair along a row), got "
                          f"{grid.rows} x {grid.cols}")
    return grid


def _check_parallel(profile: BoardProfile, where: str) -> None:
    """The ADCs must cover the grid's channels and the decoder must reach every ADC."""
    m = profile.measurement
    if m.adc_oversampling not in ADC_OVERSAMPLING:
        raise ConfigError(f"[board.measurement] adc_oversampling must be one of {ADC_OVERSAMPLING} (the AD7606's "
                          f"OS[2:0] settings), got {m.adc_oversampling}")
    if m.channels_per_adc != 8:
        raise ConfigError(f"[board.measurement] channels_per_adc must be 8 (the AD7606), got {m.channels_per_adc}")
    assert m.adc_tile_rows is not None      # a field of the chain: board_profile checked it is set
    if not 1 <= m.adc_tile_rows <= m.channels_per_adc or m.channels_per_adc % m.adc_tile_rows:
        raise ConfigError(f"[board.measurement] adc_tile_rows = {m.adc_tile_rows} must divide the "
                          f"{m.channels_per_adc} channels of an ADC")
    from appliance.drivers.channel_map import ChannelMap

    adcs = ChannelMap.of_profile(profile).n_adcs
    lines = profile.adc_address_lines
    if 2 ** len(lines) < adcs:
        raise ConfigError(f"{where}: {adcs} ADCs need {max(1, (adcs - 1).bit_length())} decoder address lines "
                          f"({ADC_ADDRESS_LINE}0 ...) but [board.gpio] has {len(lines)}")


def _check_distinct(mapping: Mapping, where: str, key) -> None:
    seen: dict = {}
    for role, value in mapping.items():
        k = key(value)
        if k in seen:
            raise ConfigError(f"{where} {role} and {seen[k]} both use {k}")
        seen[k] = role


def _require(mapping: Mapping, roles, where: str) -> None:
    missing = [role for role in roles if role not in mapping]
    if missing:
        raise ConfigError(f"{where} needs {missing[0]!r} for this board")


def _take(data: dict, key: str, kind, where: str):
    if key not in data:
        raise ConfigError(f"{where} is missing {key!r}")
    value = data.pop(key)
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise ConfigError(f"{where} {key} must be {kind.__name__}, got {value!r}")
    return value


def _section(cls, values: Mapping, where: str):
    values = dict(values)
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name not in values:
            if f.default is dataclasses.MISSING:
                raise ConfigError(f"{where} is missing {f.name!r}")
            continue
        kind = int if f.type in ("int", "int | None") else str if f.type in ("str", "str | None") else float
        value = _take(values, f.name, kind, where)
        if kind is float and not value > 0:
            raise ConfigError(f"{where} {f.name} must be positive, got {value!r}")
        if kind is int and value < 0:
            raise ConfigError(f"{where} {f.name} must not be negative, got {value!r}")
        kwargs[f.name] = value
    check_keys(values, (), where, ConfigError)
    return cls(**kwargs)


def board_table_from_file(path) -> dict:
    """The ``[board]`` table of the appliance's TOML configuration file (empty if it has none)."""
    board = read_toml(path, "configuration file", ConfigError).get("board", {})
    if not isinstance(board, dict):
        raise ConfigError(f"configuration file {path}: [board] must be a table")
    return board
