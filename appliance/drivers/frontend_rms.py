"""The reference chain: AD9833 + MCP4017 + Howland source, in-amp + AD8251, AD8436 RMS, ADS1115.

Ranges combine the AD8251 gain (analogue, taken first: it raises the signal
above the converter's noise, the thesis's "largest gain that does not saturate")
with the ADS1115's full scale (free to change, no settling). The RMS converter
is the slow part: after any change its output moves with a first-order lag,
faster for rising than for falling steps, so :meth:`settle_s` waits only as long
as the predicted step needs, and the scan engine orders readings so steps rise.
The sign of a reading, which an RMS converter loses, comes from a phase
comparator on a GPIO line.
"""

from __future__ import annotations

import math

from appliance.drivers.ad8251 import AD8251
from appliance.drivers.ad9833 import AD9833
from appliance.drivers.ads1115 import ADS1115
from appliance.drivers.bus import FALLING, PULL_UP, Board, LineRequest
from appliance.drivers.frontend import RANGING_ACCURACY, ChipCheck, FrontEnd, Range, Sample, range_ladder
from appliance.drivers.mcp4017 import MCP4017
from appliance.drivers.mcp9808 import MCP9808
from appliance.drivers.profile import BoardProfile

ADC_FULL_SCALES_V = (4.096, 2.048, 1.024, 0.512, 0.256)   # +/-6.144 V is beyond the 3.3 V supply
SMALL_STEP_FLOOR = 0.05     # settle to accuracy relative to at least this fraction of full scale


def rms_ranges(profile: BoardProfile) -> tuple[Range, ...]:
    """AD8251 gain x ADS1115 full scale; the RMS converter's range caps the output."""
    m = profile.measurement
    assert m.rms_limit_v is not None        # the chain's fields: board_profile checked they are set
    return range_ladder(((min(m.rms_limit_v, adc_fs) / (m.inamp_gain * gain), gain, adc_fs)
                         for gain in AD8251.GAINS for adc_fs in ADC_FULL_SCALES_V),
                        lambda gain, adc_fs: f"x{m.inamp_gain * gain:g}, ADC +/-{adc_fs:g} V")


def digipot_setting(profile: BoardProfile, current_a: float) -> tuple[int, float]:
    """The MCP4017 wiper nearest ``current_a`` and the current it actually gives (at least one step)."""
    full = profile.excitation.full_scale_current_a
    assert full is not None
    if not 0 < current_a <= full:
        raise ValueError(f"drive current {current_a * 1e3:g} mA is outside 0..{full * 1e3:g} mA")
    top = MCP4017.POSITIONS - 1
    wiper = max(1, min(top, round(current_a / full * top)))
    return wiper, full * wiper / top


class RMSFrontEnd(FrontEnd):
    def __init__(self, board: Board, profile: BoardProfile):
        super().__init__(board, profile)
        gpio, i2c = profile.gpio, board.i2c(profile.i2c_bus)
        dds = profile.spi["dds"]
        self.dds = AD9833(board.spi(dds.bus, dds.chip_select, mode=AD9833.SPI_MODE,
                                    max_speed_hz=min(dds.max_speed_hz, AD9833.MAX_SPEED_HZ), consumer="dds"))
        self.digipot = MCP4017(i2c, address=profile.i2c["digipot"])
        self.thermometer = MCP9808(i2c, address=profile.i2c["thermometer"])
        gain_lines = board.gpio(LineRequest(outputs={gpio["gain_a0"]: 0, gpio["gain_a1"]: 0, gpio["gain_wr"]: 1},
                                            inputs={}), consumer="AD8251 gain")
        self.pga = AD8251(gain_lines, a0=gpio["gain_a0"], a1=gpio["gain_a1"], wr=gpio["gain_wr"])
        self.inputs = board.gpio(LineRequest(outputs={}, inputs={gpio["adc_ready"]: FALLING, gpio["phase_sign"]: None},
                                             bias={gpio["adc_ready"]: PULL_UP}),     # ALERT/RDY is open drain
                                 consumer="ADC ready and phase sign")
        self.adc = ADS1115(i2c, self.clock, address=profile.i2c["adc"], ready=self.inputs,
                           ready_line=gpio["adc_ready"])
        self.ranges = rms_ranges(profile)
        self._current_a = 0.0
        self.pga.set_gain(self.ranges[0].gain)

    # -- excitation ----------------------------------------------------------------------
    def start_excitation(self, current_a: float | None = None) -> None:
        current_a = self.profile.excitation.current_a if current_a is None else current_a
        assert current_a is not None
        self._set_current(current_a)
        self.dds.start(self.profile.excitation.frequency_hz)
        self.enable_source(True)

    def _set_current(self, current_a: float) -> None:
        wiper, self._current_a = digipot_setting(self.profile, current_a)
        self.digipot.set_wiper(wiper)

    def contact_current(self) -> None:
        assert self.profile.contact.test_current_a is not None
        self._set_current(self.profile.contact.test_current_a)

    def stop_excitation(self) -> None:
        self.enable_source(False)
        self.dds.stop()

    def drive_current_a(self) -> float:
        return self._current_a

    # -- measuring -----------------------------------------------------------------------
    def set_range(self, index: int) -> None:
        gain = self.ranges[index].gain
        if gain != self.pga.gain:
            self.pga.set_gain(gain)
        self.range_index = index

    def settle_s(self, drive_changed, measure_changed, previous, target, *, ranging=False) -> float:
        """The switch's own settling, then the RMS converter's lag over the predicted output step.

        A switch takes the converter's input through zero (the drive transient, or the
        measuring multiplexer's (c, c) step), so its output may have sagged from its last
        level before it climbs to the next; the wait covers the worse of the two starts.
        """
        t = self.profile.timing
        assert t.measure_settle_s is not None and t.settle_accuracy is not None
        assert t.rms_rise_tau_s is not None and t.rms_fall_tau_s is not None
        wait = t.drive_settle_s if drive_changed else t.measure_settle_s if measure_changed else 0.0
        if previous is None or target is None or (measure_changed and self.mux.passed_unknown_pair):
            accuracy = RANGING_ACCURACY if ranging else t.settle_accuracy
            return wait + t.rms_fall_tau_s * math.log(1 / accuracy)
        before = previous[1] * self.output_scale(previous[0])
        after = target[1] * self.output_scale(target[0])
        starts = [before]
        if drive_changed or measure_changed:
            zero_s = wait if drive_changed else 2 * t.call_overhead_s
            starts.append(before * math.exp(-zero_s / t.rms_fall_tau_s))
        floor = SMALL_STEP_FLOOR * self.output_scale(target[0])
        longest = 0.0
        for start in starts:
            tau = t.rms_rise_tau_s if after >= start else t.rms_fall_tau_s
            relative_step = abs(after - start) / (t.settle_accuracy * max(after, floor))
            longest = max(longest, tau * math.log(relative_step) if relative_step > 1 else 0.0)
        return wait + longest

    def output_scale(self, range_index: int) -> float:
        """The RMS converter's output at full scale of a range, volts."""
        r = self.ranges[range_index]
        return r.full_scale_input_v * self.profile.measurement.inamp_gain * r.gain

    def converter_name(self) -> str:
        return f"ADS1115 ADC at i2c{self.profile.i2c_bus}@0x{self.profile.i2c['adc']:02X}"

    def sample(self) -> Sample:
        r = self.ranges[self.range_index]
        assert self.profile.measurement.adc_data_rate_sps is not None
        out_v, code = self.adc.read_volts("AIN0", r.second_stage, self.profile.measurement.adc_data_rate_sps)
        in_phase = self.inputs.get_values([self.profile.gpio["phase_sign"]])[self.profile.gpio["phase_sign"]]
        magnitude = out_v / (self.profile.measurement.inamp_gain * r.gain)
        volts = magnitude if in_phase else -magnitude
        return Sample(volts, out_v / self.output_scale(r.index), code,
                      sign_known=magnitude >= self.profile.measurement.sign_floor_v)

    # -- self-test -------------------------------------------------------------------------
    def self_check(self) -> list[ChipCheck]:
        return self._run_checks([
            ("MCP4017 digipot", "digipot", lambda: self.digipot.set_wiper(self.digipot.wiper())),
            ("ADS1115 ADC", "adc", self.adc.check),
            ("MCP9808 thermometer", "thermometer", self._check_thermometer)])
