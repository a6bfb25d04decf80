"""The fast chain: the AD5933 excites (VOUT through the Howland source) and measures (on-chip DFT).

Ranges combine the AD8251 gain with the AD5933's receive PGA (x1, x5). A reading
is one *Repeat frequency* point: the chip waits its settling cycles after the
command, so a multiplexer switch needs no RMS lag, only the switch's own
settling. The DFT gives a phasor, and a reading is its projection on the system
phase: the in-phase (resistive) part, with its sign, while the quadrature part
that contact capacitance adds is left out (an RMS detector would add it to the
magnitude). The system phase is measured once, on a four-electrode reading whose
sign a two-electrode one tells (:meth:`AD5933FrontEnd._measure_system_phase`), as
the datasheet calibrates phase with a known resistor: a two-electrode reading
alone would carry the contacts' capacitive phase into every projection.
"""

from __future__ import annotations

import cmath
import math

from appliance.drivers.ad5933 import AD5933
from appliance.drivers.ad8251 import AD8251
from appliance.drivers.bus import Board, LineRequest
from appliance.drivers.frontend import ChipCheck, FrontEnd, Range, Sample, range_ladder
from appliance.drivers.mcp9808 import MCP9808
from appliance.drivers.profile import BoardProfile

# Typical excitation amplitude of each output range at 3.3 V (datasheet, as the Linux driver uses them).
ACTUAL_VPP = {2.0: 1.98, 1.0: 0.970, 0.4: 0.383, 0.2: 0.198}
CONTACT_RANGE_VPP = 0.2


def ad5933_ranges(profile: BoardProfile) -> tuple[Range, ...]:
    """AD8251 gain x AD5933 receive PGA; full scale is the DFT magnitude that still means an unclipped ADC."""
    m = profile.measurement
    assert m.dft_counts_per_volt is not None and m.vin_gain is not None    # the chain's: board_profile checked
    counts_per_input_v = m.dft_counts_per_volt * m.vin_gain * m.inamp_gain * math.sqrt(2)
    return range_ladder(((AD5933.CODE_LIMIT / (counts_per_input_v * gain * pga), gain, pga)
                         for gain in AD8251.GAINS for pga in AD5933.PGA_GAINS),
                        lambda gain, pga: f"x{m.inamp_gain * gain:g}, PGA x{pga:g}")


class AD5933FrontEnd(FrontEnd):
    def __init__(self, board: Board, profile: BoardProfile):
        super().__init__(board, profile)
        gpio, i2c = profile.gpio, board.i2c(profile.i2c_bus)
        self.impedance = AD5933(i2c, self.clock, address=profile.i2c["impedance"])
        self.thermometer = MCP9808(i2c, address=profile.i2c["thermometer"])
        gain_lines = board.gpio(LineRequest(outputs={gpio["gain_a0"]: 0, gpio["gain_a1"]: 0, gpio["gain_wr"]: 1},
                                            inputs={}), consumer="AD8251 gain")
        self.pga = AD8251(gain_lines, a0=gpio["gain_a0"], a1=gpio["gain_a1"], wr=gpio["gain_wr"])
        self.ranges = ad5933_ranges(profile)
        assert profile.excitation.output_range_vpp is not None      # the chain's: board_profile checked
        self.output_range_vpp: float = profile.excitation.output_range_vpp
        self.system_phase: float | None = None
        self.pga.set_gain(self.ranges[0].gain)

    def _counts_per_volt(self, r: Range) -> float:
        m = self.profile.measurement
        assert m.dft_counts_per_volt is not None and m.vin_gain is not None
        return m.dft_counts_per_volt * m.vin_gain * m.inamp_gain * math.sqrt(2) * r.gain * int(r.second_stage)

    # -- excitation ----------------------------------------------------------------------
    def start_excitation(self, current_a: float | None = None) -> None:
        vpp = self.profile.excitation.output_range_vpp
        assert vpp is not None and self.profile.measurement.settling_cycles is not None
        if current_a is not None:
            fitting = [v for v in ACTUAL_VPP if self._current_of(v) <= current_a * 1.0001]
            if not fitting:
                raise ValueError(f"drive current {current_a * 1e3:g} mA is below the smallest output range")
            vpp = max(fitting)
        self.impedance.configure(self.profile.excitation.frequency_hz,
                                 settling_cycles=self.profile.measurement.settling_cycles,
                                 output_range_vpp=vpp, pga_gain=int(self.ranges[self.range_index].second_stage))
        self.output_range_vpp = vpp
        self.enable_source(True)
        self.impedance.start()
        if self.system_phase is None:
            self._measure_system_phase()

    def _current_of(self, vpp: float) -> float:
        assert self.profile.excitation.transconductance_a_per_v is not None
        return ACTUAL_VPP[vpp] / (2 * math.sqrt(2)) * self.profile.excitation.transconductance_a_per_v

    def _measure_system_phase(self) -> None:
        """The phase every positive reading has: that of a four-electrode reading (the sheet is resistive, so
        it carries the electronics' phase alone), its sign told by a two-electrode reading at the smallest
        excitation (always positive, but shifted by the contacts' capacitance, up to a quarter turn)."""
        before = self.output_range_vpp
        self.impedance.set_output_range(CONTACT_RANGE_VPP)
        self.mux.select((1, 2), (1, 2))
        self.set_range(0)
        self.clock.sleep(self.profile.timing.drive_settle_s)
        two = cmath.phase(self.impedance.measure())
        self.impedance.set_output_range(before)
        self.system_phase = two
        if self.profile.channels >= 4:
            self.mux.select((1, 2), (3, 4))
            self.clock.sleep(self.profile.timing.drive_settle_s)
            z = self.impedance.measure()
            if not AD5933.is_saturated(z) and abs(z) > 0:
                four = cmath.phase(z)
                self.system_phase = min((four, four + math.pi), key=lambda p: abs(cmath.phase(cmath.rect(1, p - two))))
        self.forget_routing()

    def contact_current(self) -> None:
        self.impedance.set_output_range(CONTACT_RANGE_VPP)
        self.output_range_vpp = CONTACT_RANGE_VPP

    def stop_excitation(self) -> None:
        self.enable_source(False)
        self.impedance.power_down()

    def sample_source_off(self) -> Sample:
        """The converter must run to measure, so only the current source is switched off."""
        self.start_excitation()
        self.enable_source(False)
        return self.sample()

    def drive_current_a(self) -> float:
        return self._current_of(self.output_range_vpp)

    # -- measuring -----------------------------------------------------------------------
    def set_range(self, index: int) -> None:
        r = self.ranges[index]
        if r.gain != self.pga.gain:
            self.pga.set_gain(r.gain)
        if int(self.ranges[index].second_stage) != int(self.ranges[self.range_index].second_stage):
            self.impedance.set_pga(int(self.ranges[index].second_stage))
        self.range_index = index

    def settle_s(self, drive_changed, measure_changed, previous, target, *, ranging=False) -> float:
        t = self.profile.timing
        assert t.measure_settle_s is not None
        return t.drive_settle_s if drive_changed else t.measure_settle_s if measure_changed else 0.0

    def sample(self) -> Sample:
        r = self.ranges[self.range_index]
        z = self.impedance.measure()
        magnitude = abs(z) / self._counts_per_volt(r)
        if AD5933.is_saturated(z):
            return Sample(magnitude, 1.0, z)
        phase = self.system_phase if self.system_phase is not None else 0.0
        in_phase = magnitude * math.cos(cmath.phase(z) - phase)
        return Sample(in_phase, abs(z) / AD5933.CODE_LIMIT, z,
                      sign_known=magnitude >= self.profile.measurement.sign_floor_v)

    def converter_name(self) -> str:
        return f"AD5933 at i2c{self.profile.i2c_bus}@0x{self.profile.i2c['impedance']:02X}"

    # -- self-test -------------------------------------------------------------------------
    def self_check(self) -> list[ChipCheck]:
        return self._run_checks([("AD5933 impedance converter", "impedance", self._check_converter),
                                 ("MCP9808 thermometer", "thermometer", self._check_thermometer)])

    def _check_converter(self) -> str:
        assert self.profile.measurement.settling_cycles is not None
        self.impedance.configure(self.profile.excitation.frequency_hz,
                                 settling_cycles=self.profile.measurement.settling_cycles,
                                 output_range_vpp=self.output_range_vpp, pga_gain=1)
        return f"start frequency reads back; die at {self.impedance.temperature_c():.1f} degC"
