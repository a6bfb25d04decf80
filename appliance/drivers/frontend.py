"""The front end as the scan engine sees it: select electrodes, pick a range, wait, take a sample.

A :class:`FrontEnd` composes the chip drivers of one board profile (built by
:func:`~appliance.drivers.backend.open_front_end`). Both chains (RMS converter and ADC, or AD5933) offer the
same operations, so the scan engine's ordering, auto-ranging and fault handling
are written once; the parallel chain (``frontend_parallel``) reads all of a
drive's pairs in one step instead. Electrodes are 1-based here, multiplexer channels 0-based in
the chip drivers: electrode e is channel e - 1.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from appliance.drivers.adg7xx import ADG725, ADG731
from appliance.drivers.bus import Board, LineRequest
from appliance.drivers.mcp9808 import MCP9808
from appliance.drivers.profile import BoardProfile
from appliance.errors import ApplianceError, ChipError, ConfigError


@dataclass(frozen=True)
class Range:
    """One gain setting of the chain and the input it can take (volts rms, input-referred).

    ``gain`` is the AD8251's; ``second_stage`` the converter's own setting (the
    ADS1115's full scale in volts, or the AD5933's PGA gain).
    """

    index: int
    gain: float
    second_stage: float
    full_scale_input_v: float
    label: str


def range_ladder(candidates, label) -> tuple[Range, ...]:
    """Distinct full scales from (full_scale_input_v, gain, second_stage) candidates, least sensitive first.

    Where two settings reach the same full scale the larger analogue gain wins: it
    lifts the signal above the converter's noise (the thesis's rule).
    """
    best: dict[float, tuple[float, float, float]] = {}
    for full_scale, gain, second in candidates:
        key = round(full_scale, 12)
        if key not in best or gain > best[key][1]:
            best[key] = (full_scale, gain, second)
    ordered = sorted(best.values(), reverse=True)
    return tuple(Range(i, gain, second, fs, label(gain, second)) for i, (fs, gain, second) in enumerate(ordered))


@dataclass(frozen=True)
class Sample:
    """One conversion at one range.

    ``volts`` is the input-referred differential V(meas+) - V(meas-) in volts rms
    (its sign from the chain's phase detection), ``fraction`` the share of the
    range's full scale used, ``raw`` what the converter returned.
    """

    volts: float
    fraction: float
    raw: object
    sign_known: bool = True


@dataclass(frozen=True)
class Measured:
    """A reading taken at the range auto-ranging settled on; ``saturated`` if even the least
    sensitive range was over."""

    sample: Sample
    range_index: int
    saturated: bool


PLAUSIBLE_TEMPERATURE_C = (5.0, 45.0)
RANGING_ACCURACY = 0.05    # a probe that only picks the range settles to this
OVER_RANGE = 0.97          # a sample above this fraction of full scale may be clipped
MAX_RANGE_STEPS = 4


@dataclass(frozen=True)
class ChipCheck:
    """The answer of one chip to the self-test: where it is, and whether it read back right."""

    part: str
    where: str
    ok: bool
    detail: str


class Multiplexers:
    """The drive and measuring multiplexers: ADG725 pairs (A and B halves) or four ADG731s."""

    def __init__(self, board: Board, profile: BoardProfile):
        def spi(role, cls):
            address = profile.spi[role]
            return cls(board.spi(address.bus, address.chip_select, mode=cls.SPI_MODE,
                                 max_speed_hz=min(address.max_speed_hz, cls.MAX_SPEED_HZ), consumer=role))

        self.kind = profile.multiplexer
        self.channels = profile.channels
        if self.kind == "adg725":
            self.drive, self.measure = spi("drive_mux", ADG725), spi("measure_mux", ADG725)
        else:
            self.parts = [spi(role, ADG731) for role in ("drive_pos_mux", "drive_neg_mux", "meas_pos_mux",
                                                         "meas_neg_mux")]
        self.drive_pair: tuple[int, int] | None = None
        self.measure_pair: tuple[int, int] | None = None
        self.passed_unknown_pair = False     # the last switch went through an unplanned measuring pair

    def check_electrodes(self, n_electrodes: int) -> None:
        if n_electrodes > self.channels:
            raise ConfigError(f"the layout has {n_electrodes} electrodes but the board's {self.kind} "
                              f"multiplexers reach {self.channels}")

    def select(self, drive: tuple[int, int], measure: tuple[int, int]) -> tuple[bool, bool]:
        """Route the pairs (1-based electrodes); returns (drive changed, measure changed)."""
        drive_changed, measure_changed = drive != self.drive_pair, measure != self.measure_pair
        if self.kind == "adg725":
            if drive_changed:
                self.drive.select(*self._changed(drive, self.drive_pair))
            if measure_changed:
                a, b = self._changed(measure, self.measure_pair)
                if a is not None and b is not None:
                    # One word moves one half at a time; via (c, c) the in-amp sees zero between
                    # the two words, not an unknown pair that would kick the RMS converter.
                    self.measure.select(a, a)
                    a = None
                self.measure.select(a, b)
        else:
            old = (self.drive_pair or (None, None)) + (self.measure_pair or (None, None))
            for part, new, before in zip(self.parts, drive + measure, old):
                if new != before:
                    part.select(new - 1)
            # Two separate measuring muxes pass through a pair nobody asked for.
            self.passed_unknown_pair = measure[0] != old[2] and measure[1] != old[3]
        self.drive_pair, self.measure_pair = drive, measure
        return drive_changed, measure_changed

    @staticmethod
    def _changed(new: tuple[int, int], old: tuple[int, int] | None) -> tuple[int | None, int | None]:
        before: tuple[int | None, int | None] = old or (None, None)
        return (None if new[0] == before[0] else new[0] - 1, None if new[1] == before[1] else new[1] - 1)

    def off(self) -> None:
        for part in ([self.drive, self.measure] if self.kind == "adg725" else self.parts):
            part.off()
        self.drive_pair = self.measure_pair = None


class FrontEnd(ABC):
    """A board's measurement chain behind one interface; see the module docstring.

    It takes one reading at a time. A chain that reads every measuring pair of a
    drive at once (:class:`~appliance.drivers.frontend_parallel.ParallelFrontEnd`)
    offers steps instead, with ``parallel = True``; the scan engine runs either.
    """

    parallel = False
    profile: BoardProfile
    ranges: tuple[Range, ...]          # least sensitive first
    mux: Multiplexers
    thermometer: MCP9808

    def __init__(self, board: Board, profile: BoardProfile):
        self.board, self.profile, self.clock = board, profile, board.clock
        self.mux = Multiplexers(board, profile)
        self.outputs = board.gpio(LineRequest(outputs={profile.gpio["source_enable"]: 0}, inputs={}),
                                  consumer="current source enable")
        self.range_index = 0
        self.level: tuple[int, float] | None = None     # range and fraction of the last sample

    def check_electrodes(self, n_electrodes: int) -> None:
        """Refuse a layout with more electrodes than the multiplexers reach."""
        self.mux.check_electrodes(n_electrodes)

    @abstractmethod
    def start_excitation(self, current_a: float | None = None) -> None:
        """Switch the sine on at the profile's frequency and ``current_a`` (default: the profile's)."""

    @abstractmethod
    def stop_excitation(self) -> None:
        """Current source off and the sine stopped: the safe state."""

    @abstractmethod
    def set_range(self, index: int) -> None:
        """Switch to ``ranges[index]``."""

    @abstractmethod
    def settle_s(self, drive_changed: bool, measure_changed: bool, previous: tuple[int, float] | None,
                 target: tuple[int, float] | None, *, ranging: bool = False) -> float:
        """How long to wait before sampling after these changes.

        ``previous`` and ``target`` are (range index, fraction of full scale) of the
        last sample and of the one expected next, None where unknown. A ``ranging``
        sample only picks the range, so a few per cent of accuracy will do.
        """

    def output_scale(self, range_index: int) -> float:
        """What one full-scale fraction means at the converter's input in this range (for ordering)."""
        return 1.0

    @abstractmethod
    def converter_name(self) -> str:
        """The part that digitises readings, with its address (for technical conditions)."""

    @abstractmethod
    def sample(self) -> Sample:
        """One conversion at the present range."""

    @abstractmethod
    def drive_current_a(self) -> float:
        """The excitation current now set, amps rms."""

    @abstractmethod
    def contact_current(self) -> None:
        """Lower the excitation to the profile's contact-test current."""

    @abstractmethod
    def self_check(self) -> list[ChipCheck]:
        """Ask each chip to answer and read back."""

    def _run_checks(self, checks) -> list[ChipCheck]:
        """Run (part, bus role, action) checks on the I2C chips."""
        return run_checks([(part, f"i2c{self.profile.i2c_bus}@0x{self.profile.i2c[role]:02X}", action)
                           for part, role, action in checks])

    def _check_thermometer(self) -> str:
        return check_thermometer(self.thermometer)

    def sample_source_off(self) -> Sample:
        """One sample with the current source off (the self-test's zero): what remains is offset and pickup."""
        self.stop_excitation()
        return self.sample()

    def enable_source(self, on: bool) -> None:
        self.outputs.set_values({self.profile.gpio["source_enable"]: int(on)})

    def measure(self, drive: tuple[int, int], measure: tuple[int, int], *, range_index: int | None = None,
                expected_fraction: float | None = None, conversions: int = 1) -> Measured:
        """Route the pairs and auto-range: the largest gain that does not saturate.

        Starts at ``range_index`` (a plan from an earlier frame, with the fraction it
        expects) or at the least sensitive range, and moves at most a few steps.
        """
        drive_changed, measure_changed = self.mux.select(drive, measure)
        r = 0 if range_index is None else range_index
        expected = expected_fraction if range_index is not None else None
        for step in range(MAX_RANGE_STEPS):
            self.set_range(r)
            target = (r, expected) if expected is not None else None
            probing = step == 0 and target is None      # only picks the range; never the final sample
            self.clock.sleep(self.settle_s(drive_changed, measure_changed, self.level, target, ranging=probing))
            drive_changed = measure_changed = False
            sample = self._averaged(conversions)
            self.level = (r, sample.fraction)
            if sample.fraction > OVER_RANGE:
                if r == 0 and not probing:
                    return Measured(sample, r, True)
                r, expected = max(0, min(r - 1, self.best_range(2 * sample.volts))), None
                continue
            best = self.best_range(sample.volts)
            if best == r and not probing:
                break
            expected = sample.fraction * self.ranges[r].full_scale_input_v / self.ranges[best].full_scale_input_v
            r = best
        return Measured(sample, r, False)

    def _averaged(self, conversions: int) -> Sample:
        samples = [self.sample() for _ in range(conversions)]
        if conversions == 1:
            return samples[0]
        return Sample(float(np.mean([s.volts for s in samples])), float(np.mean([s.fraction for s in samples])),
                      samples[-1].raw, all(s.sign_known for s in samples))

    def forget_routing(self) -> None:
        """After a failed transfer the chips' state is unknown: route and settle afresh next time."""
        self.mux.drive_pair = self.mux.measure_pair = None
        self.level = None

    def best_range(self, volts: float) -> int:
        """The most sensitive range that keeps ``volts`` below the profile's headroom."""
        headroom = self.profile.measurement.range_headroom
        fitting = [r.index for r in self.ranges if abs(volts) <= headroom * r.full_scale_input_v]
        return max(fitting) if fitting else 0

    def close(self) -> None:
        """Leave the front end safe (no current, switches open); the board releases the buses."""
        self.stop_excitation()
        self.mux.off()


def run_checks(checks) -> list[ChipCheck]:
    """Run (part, where, action) checks; a failure is reported with its message, not raised."""
    results = []
    for part, where, action in checks:
        try:
            results.append(ChipCheck(part, where, True, action() or "answers and reads back"))
        except (ApplianceError, OSError) as exc:
            results.append(ChipCheck(part, where, False, str(exc)))
    return results


def check_thermometer(thermometer) -> str:
    """The MCP9808 answers as itself and reads a temperature a ward can have."""
    thermometer.check_identity()
    temperature = thermometer.temperature_c()
    if not PLAUSIBLE_TEMPERATURE_C[0] <= temperature <= PLAUSIBLE_TEMPERATURE_C[1]:
        raise ChipError(f"MCP9808 reads {temperature:.2f} degC, outside the plausible "
                        f"{PLAUSIBLE_TEMPERATURE_C[0]:g}..{PLAUSIBLE_TEMPERATURE_C[1]:g} degC of a ward")
    return f"{temperature:.2f} degC"
