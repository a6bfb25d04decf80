"""The parallel chain: one excitation switched to any drive pair, a demodulating channel on every pair along the rows.

AD9833 + MCP4017 + Howland source (as on the reference board) feed the I+ and
I- buses; the ADG1414 drive matrix puts one electrode on each in one transfer.
Every horizontally adjacent pair has its own in-amp, synchronous demodulator
and low-pass, and the AD7606s sample all of them at one CONVST edge. So a
*step* (one drive) yields every reading of that drive at once: route, wait for
the low-passes, convert, read the converters that hold the channels wanted.

A step's sample is taken at the CONVST edge (the AD7606s' track-and-hold), so
the next drive may be routed straight after it: its low-passes settle while
this step's converters are read out (``then``). Its two ranges are the
AD7606's RANGE pin (+/-10 V and +/-5 V) behind a fixed gain chosen so that the
bed's readings fit (``benchmarks/acquisition.md``); the demodulator gives each
reading its sign. Channel offsets after the demodulator are measured with the
source off (:meth:`measure_zero`) and subtracted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from appliance.drivers.ad7606 import FULL_SCALES_V, AD7606Array
from appliance.drivers.ad9833 import AD9833
from appliance.drivers.adg1414 import ADG1414Chain, DriveMatrix
from appliance.drivers.bus import Board, LineRequest
from appliance.drivers.channel_map import ChannelMap
from appliance.drivers.decoder import ChipSelectDecoder
from appliance.drivers.frontend import ChipCheck, Range, check_thermometer, run_checks
from appliance.drivers.frontend_rms import digipot_setting
from appliance.drivers.mcp4017 import MCP4017
from appliance.drivers.mcp9808 import MCP9808
from appliance.drivers.profile import BoardProfile
from appliance.errors import ChipReadbackMismatch, ConfigError

DEMODULATOR_GAIN = 2 * math.sqrt(2) / math.pi
"""Mean output of a full-wave synchronous demodulator per volt rms of an in-phase sine."""
ZERO_FRAMES = 8
"""Offsets are a running mean of this many zero measurements: drift is slow, and the mean's noise is small."""


def parallel_ranges(profile: BoardProfile) -> tuple[Range, ...]:
    """The AD7606's two ranges behind the fixed gain, least sensitive first (input-referred volts rms)."""
    m = profile.measurement
    assert m.lowpass_gain is not None           # the chain's: board_profile checked it is set
    gain = m.inamp_gain * DEMODULATOR_GAIN * m.lowpass_gain
    return tuple(Range(i, gain, fs, fs / gain, f"x{gain:.1f}, ADC +/-{fs:g} V") for i, fs in enumerate(FULL_SCALES_V))


@dataclass(frozen=True)
class StepSample:
    """What one step read: per channel asked for, V(first) - V(second) in volts rms (input-referred, offset
    removed), the share of the range's full scale its code used, the code, and the ADC it came from."""

    volts: np.ndarray
    fraction: np.ndarray
    codes: np.ndarray
    adcs: np.ndarray
    range_index: int
    sampled_at_s: float


class ParallelFrontEnd:
    """A board's parallel chain; see the module docstring. Electrodes are 1-based."""

    parallel = True

    def __init__(self, board: Board, profile: BoardProfile):
        self.board, self.profile, self.clock = board, profile, board.clock
        self.cmap = ChannelMap.of_profile(profile)
        gpio, i2c = profile.gpio, board.i2c(profile.i2c_bus)
        self.outputs = board.gpio(LineRequest(outputs={gpio["source_enable"]: 0}, inputs={}),
                                  consumer="current source enable")
        dds = profile.spi["dds"]
        self.dds = AD9833(board.spi(dds.bus, dds.chip_select, mode=AD9833.SPI_MODE,
                                    max_speed_hz=min(dds.max_speed_hz, AD9833.MAX_SPEED_HZ), consumer="dds"))
        self.digipot = MCP4017(i2c, address=profile.i2c["digipot"])
        self.thermometer = MCP9808(i2c, address=profile.i2c["thermometer"])
        chips = DriveMatrix.chips_for(profile.channels)
        sw = profile.spi["drive_switches"]
        chain = ADG1414Chain(board.spi(sw.bus, sw.chip_select, mode=ADG1414Chain.SPI_MODE,
                                       max_speed_hz=min(sw.max_speed_hz, ADG1414Chain.speed_limit_hz(chips)),
                                       consumer="drive switches"), chips)
        self.switches = DriveMatrix(chain, profile.channels)
        adc = profile.spi["adc"]
        names = dict(convst=gpio["adc_convst"], busy=gpio["adc_busy"], reset=gpio["adc_reset"],
                     range_line=gpio["adc_range"])
        lines = board.gpio(AD7606Array.line_request(address_lines=profile.adc_address_lines, **names),
                           consumer="AD7606 converters")
        spi = board.spi(adc.bus, adc.chip_select, mode=AD7606Array.SPI_MODE,
                        max_speed_hz=min(adc.max_speed_hz, AD7606Array.MAX_SPEED_HZ), consumer="AD7606 converters")
        self.adc_device = spi.name
        assert profile.measurement.adc_oversampling is not None
        self.adcs = AD7606Array(lines, self.clock, ChipSelectDecoder(spi, lines, profile.adc_address_lines),
                                n_chips=self.cmap.n_adcs, oversampling=profile.measurement.adc_oversampling, **names)
        self.ranges = parallel_ranges(profile)
        self.gain = self.ranges[0].gain
        self.offset_v = np.zeros(self.cmap.n_channels)      # at the ADC input, per channel
        self._zeros = 0
        self._current_a = 0.0
        self.routed_at = -math.inf
        self.switches.off()
        self.adcs.reset()

    # -- excitation ----------------------------------------------------------------------
    def start_excitation(self, current_a: float | None = None) -> None:
        """Sine on at the profile's frequency and ``current_a`` (default: the profile's), source enabled."""
        current_a = self.profile.excitation.current_a if current_a is None else current_a
        assert current_a is not None
        self._set_current(current_a)
        self.dds.start(self.profile.excitation.frequency_hz)
        self.enable_source(True)
        self.routed_at = self.clock.monotonic()

    def _set_current(self, current_a: float) -> None:
        wiper, self._current_a = digipot_setting(self.profile, current_a)
        self.digipot.set_wiper(wiper)

    def contact_current(self) -> None:
        assert self.profile.contact.test_current_a is not None
        self._set_current(self.profile.contact.test_current_a)
        self.routed_at = self.clock.monotonic()

    def stop_excitation(self) -> None:
        self.enable_source(False)
        self.dds.stop()

    def drive_current_a(self) -> float:
        return self._current_a

    def enable_source(self, on: bool) -> None:
        self.outputs.set_values({self.profile.gpio["source_enable"]: int(on)})

    # -- channels and steps ----------------------------------------------------------------
    def check_electrodes(self, n_electrodes: int) -> None:
        g = self.profile.grid
        assert g is not None                        # a parallel profile has its grid
        if n_electrodes != g.rows * g.cols:
            raise ConfigError(f"the layout has {n_electrodes} electrodes but the parallel front end is built for a "
                              f"{g.rows} x {g.cols} grid ({g.rows * g.cols}); set [board.grid] to the mat's")

    def route(self, drive: tuple[int, int]) -> None:
        """Current into ``drive[0]`` and out of ``drive[1]`` (one transfer); the low-passes start settling."""
        drive = (int(drive[0]), int(drive[1]))
        if self.switches.pair != drive:
            self.switches.route(*drive)
            self.routed_at = self.clock.monotonic()

    def step(self, drive: tuple[int, int], channels, range_index: int, *,
             then: tuple[int, int] | None = None) -> StepSample:
        """One conversion of every channel with ``drive`` routed; the readings of ``channels``.

        ``then`` is the next drive: it is routed as soon as the sample is held, so
        its settling overlaps this step's read-out.
        """
        channels = np.asarray(channels, dtype=np.int64)
        self.route(drive)
        full_scale = self.ranges[range_index].second_stage
        self.adcs.set_range(full_scale)
        self.clock.sleep(max(0.0, self.routed_at + self.profile.timing.drive_settle_s - self.clock.monotonic()))
        self.adcs.convert()
        sampled_at = self.clock.monotonic()
        if then is not None:
            self.route(then)
        where = self.cmap.adc_index[channels]
        read = self.adcs.read_many(where[:, 0].tolist())
        codes = np.array([read[int(a)][int(i)] for a, i in where], dtype=np.int64).reshape(-1)
        pin_v = codes * (full_scale / 32768)
        return StepSample((pin_v - self.offset_v[channels]) / self.gain, np.abs(codes) / 32768, codes, where[:, 0],
                          range_index, sampled_at)

    def measure_zero(self) -> None:
        """Every channel with the source off: their offsets, as a running mean over the last few frames."""
        self.enable_source(False)
        self.switches.off()
        self.routed_at = self.clock.monotonic()
        self.clock.sleep(self.profile.timing.drive_settle_s)
        full_scale = self.ranges[-1].second_stage
        self.adcs.set_range(full_scale)
        self.adcs.convert()
        read = self.adcs.read_many(range(self.cmap.n_adcs))
        where = self.cmap.adc_index
        zero = np.array([read[int(a)][int(i)] for a, i in where]) * (full_scale / 32768)
        self._zeros = min(self._zeros + 1, ZERO_FRAMES)
        self.offset_v += (zero - self.offset_v) / self._zeros

    def best_range(self, volts) -> int:
        """The most sensitive range that keeps every reading of ``volts`` below the profile's headroom."""
        peak = float(np.max(np.abs(volts))) if np.size(volts) else 0.0
        headroom = self.profile.measurement.range_headroom
        fitting = [r.index for r in self.ranges if peak <= headroom * r.full_scale_input_v]
        return max(fitting) if fitting else 0

    def converter_name(self, adc: int | None = None) -> str:
        where = f"on {self.adc_device}"
        return f"AD7606 converters {where}" if adc is None else f"AD7606 {adc} {where} (decoder output {adc})"

    def forget_routing(self) -> None:
        """After a failed transfer the chips' state is unknown: route, address and settle afresh next time."""
        self.switches.forget()
        self.adcs.forget()
        self.routed_at = -math.inf

    # -- self-test -------------------------------------------------------------------------
    def self_check(self) -> list[ChipCheck]:
        """Chips that answer: the digipot and thermometer read back, the switch chain shifts a pattern
        through every chip and back (its length and wiring)."""
        return run_checks([
            ("MCP4017 digipot", f"i2c{self.profile.i2c_bus}@0x{self.profile.i2c['digipot']:02X}",
             lambda: self.digipot.set_wiper(self.digipot.wiper())),
            ("MCP9808 thermometer", f"i2c{self.profile.i2c_bus}@0x{self.profile.i2c['thermometer']:02X}",
             lambda: check_thermometer(self.thermometer)),
            ("ADG1414 drive switches", self.switches.chain.spi.name, self._check_switch_chain)])

    def _check_switch_chain(self) -> str:
        """With the source off, shift the words of drive 1 -> 2 in and out again: SDO must return them."""
        self.enable_source(False)
        chain = self.switches.chain
        pattern = DriveMatrix.words_for(1, 2, n_chips=chain.chips)
        chain.off()
        chain.write(pattern)
        back = chain.write([0] * chain.chips)
        self.switches.pair = None
        if back != bytes(reversed(pattern)):
            raise ChipReadbackMismatch(f"ADG1414 chain of {chain.chips}: wrote {bytes(reversed(pattern)).hex()}, "
                                       f"shifted out {back.hex()} (a chip missing, or the chain's length wrong)")
        return f"{chain.chips} chips shift a pattern through and back"

    def close(self) -> None:
        """Leave the front end safe (no current, switches open); the board releases the buses."""
        self.stop_excitation()
        self.switches.off()
