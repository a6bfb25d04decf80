"""The analogue chain applied to a whole frame at once: the virtual bed's fast path.

The emulated board runs the chips one transfer at a time, which is right for
testing drivers and too slow for a bed-size mat at a frame a second. This
module gives the same readings a settled scan would: the current source's
compliance, each reading auto-ranged to the largest gain that does not
saturate (the profile's range ladder), the chain's gain errors
(:class:`~appliance.drivers.emulated.analogue.ChainErrors`), its noise, the
converter's quantisation at that range, saturation at the least sensitive
range, and the sign lost below the phase comparator's floor. Given the
electrodes' contacts (:class:`~appliance.drivers.emulated.electrode_interface.ElectrodeContact`,
R parallel C), each reading is the profile's detector's view of the complex
differential: the RMS chain's magnitude, quadrature included, or the in-phase
part of the AD5933's DFT and the parallel board's synchronous demodulators.
Drives that need more than the source's compliance are flagged COMPLIANCE.

>>> import numpy as np
>>> from appliance.core.protocols import adjacent_protocol
>>> from appliance.drivers.profile import board_profile
>>> chain = FrameChain(board_profile({}), seed=1)
>>> z = np.array([[6., 2, 1, 2], [2, 6, 2, 1], [1, 2, 6, 2], [2, 1, 2, 6]])     # ohm
>>> volts, flags = chain.readings(z, adjacent_protocol(4))
>>> np.round(volts * 1e3, 2).tolist(), flags.tolist()             # mV at 2.02 mA
([-4.03, -4.03, -4.03, -4.03], [0, 0, 0, 0])
>>> volts, flags = chain.readings(10 * z, adjacent_protocol(4))   # beyond the least sensitive range
>>> volts.tolist(), flags.tolist()
([nan, nan, nan, nan], [1, 1, 1, 1])
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from appliance.core.protocols import Protocol
from appliance.drivers.emulated.analogue import ChainErrors, compliant_current
from appliance.drivers.emulated.electrode_interface import ElectrodeContact, detect, reading_phasors
from appliance.drivers.frontend import OVER_RANGE
from appliance.drivers.profile import BoardProfile
from appliance.drivers.scan import Flag

if TYPE_CHECKING:
    from appliance.drivers.emulated.parallel import ParallelErrors


class FrameChain:
    """Readings of a whole frame from transfer impedances, as the profile's front end would take them.

    A ``parallel`` profile gets :class:`ParallelFrameChain`.
    """

    def __new__(cls, profile: BoardProfile, **kwargs):
        if cls is FrameChain and profile.chain == "parallel":
            cls = ParallelFrameChain
        return super().__new__(cls)

    def __init__(self, profile: BoardProfile, *, errors: ChainErrors | None = None, seed: int = 0,
                 contact: ElectrodeContact | None = None):
        self.profile, self.contact = profile, contact
        self.at_compliance = np.zeros(0, dtype=bool)
        self.rng = np.random.default_rng(seed)
        self.errors = errors or ChainErrors.drawn(np.random.default_rng(seed))
        if profile.chain == "rms":
            from appliance.drivers.frontend_rms import digipot_setting, rms_ranges

            self.ranges = rms_ranges(profile)
            assert profile.excitation.current_a is not None     # the chain's: board_profile checked it is set
            self.current_a = digipot_setting(profile, profile.excitation.current_a)[1]
        else:
            from appliance.drivers.frontend_ad5933 import ACTUAL_VPP, ad5933_ranges

            self.ranges = ad5933_ranges(profile)
            x = profile.excitation
            assert x.output_range_vpp is not None and x.transconductance_a_per_v is not None
            self.current_a = ACTUAL_VPP[x.output_range_vpp] / (2 * np.sqrt(2)) * x.transconductance_a_per_v
        self.full_scale = np.array([r.full_scale_input_v for r in self.ranges])
        self.gain = np.array([r.gain for r in self.ranges])

    def check(self, protocol: Protocol) -> None:
        """Refuse a protocol this front end cannot take (every reading suits the serial chains)."""

    def ideal(self, transfer: np.ndarray, protocol: Protocol) -> np.ndarray:
        """V(meas+) - V(meas-) at the set current (less where the source reaches compliance), volts rms,
        as the detector reports it; :attr:`at_compliance` marks the readings whose drive hit compliance."""
        return self._detected(transfer, protocol, 0.0)[0]

    def _detected(self, transfer: np.ndarray, protocol: Protocol, series_ohm: float,
                  phase_error_rad: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(what the detector reports, the quadrature part it was given), volts rms."""
        a, b, c, d = (protocol.readings - 1).T
        z, compliance = transfer, self.profile.excitation.compliance_v
        assert compliance is not None                   # board_profile sets it
        if self.contact is None:
            drive_ohm = z[a, a] - z[a, b] - z[b, a] + z[b, b] + series_ohm
            current = compliant_current(self.current_a, drive_ohm, compliance)
            self.at_compliance = self.current_a * np.abs(drive_ohm) > compliance
            return current * (z[c, a] - z[c, b] - z[d, a] + z[d, b]), np.zeros(len(a))
        x, m = self.profile.excitation, self.profile.measurement
        assert m.detector is not None                   # board_profile sets it
        phasors, _, self.at_compliance = reading_phasors(z, protocol.readings - 1, self.current_a, self.contact,
                                                         x.frequency_hz, m.input_capacitance_f or 0.0, compliance,
                                                         series_ohm)
        return detect(phasors, m.detector, phase_error_rad), phasors.imag

    def ranges_for(self, volts: np.ndarray) -> np.ndarray:
        """The most sensitive range keeping each reading under the headroom (0 where none does)."""
        fits = np.abs(volts)[:, None] <= self.profile.measurement.range_headroom * self.full_scale[None, :]
        return np.where(fits.any(axis=1), fits.shape[1] - 1 - np.argmax(fits[:, ::-1], axis=1), 0)

    def readings(self, transfer: np.ndarray, protocol: Protocol) -> tuple[np.ndarray, np.ndarray]:
        """(volts, flags) of one frame; saturated readings are NaN and flagged, as a scan leaves them."""
        ideal = self.ideal(transfer, protocol)
        r = self.ranges_for(ideal)
        m = self.profile.measurement
        total_gain = m.inamp_gain * self.gain[r]
        level = np.abs(ideal) * total_gain * self.errors.gain_factor(self.gain[r])
        noisy = level + self.errors.output_noise_v(total_gain, level) * self.rng.standard_normal(len(ideal))
        step = self._step(r, total_gain)
        measured = np.round(np.clip(noisy, 0, None) / step) * step / total_gain
        flags = np.zeros(len(ideal), dtype=np.int64)
        flags[self.at_compliance] |= Flag.COMPLIANCE
        saturated = (r == 0) & (np.abs(ideal) > OVER_RANGE * self.full_scale[0])
        flags[saturated] |= Flag.SATURATED
        unsure = measured < m.sign_floor_v
        flags[unsure] |= Flag.SIGN_UNCERTAIN
        sign = np.where(unsure, self.rng.choice([-1.0, 1.0], len(ideal)), np.sign(ideal))
        return np.where(saturated, np.nan, sign * measured), flags

    def _step(self, r: np.ndarray, total_gain: np.ndarray) -> np.ndarray:
        """The converter's quantum at each reading's range, at its output (volts)."""
        if self.profile.chain == "rms":
            adc_full_scale = np.array([rng.second_stage for rng in self.ranges])[r]
            return adc_full_scale / 32768
        m = self.profile.measurement
        pga = np.array([rng.second_stage for rng in self.ranges])[r]
        assert m.dft_counts_per_volt is not None and m.vin_gain is not None
        # One DFT count, referred to the RMS level after the in-amp and AD8251.
        return 1.0 / (m.dft_counts_per_volt * m.vin_gain * np.sqrt(2) * pga)


class ParallelFrameChain(FrameChain):
    """The parallel front end's frame: every drive's readings from one conversion, ranged per drive.

    Per reading: the current source's current (less at compliance, through the
    two switches' on resistance), the channel's gain, quadrature leak and
    offset (:class:`~appliance.drivers.emulated.parallel.ParallelErrors`, drawn as
    the emulated board draws them for the same ``seed``), the in-amp and
    converter noise, the AD7606 code at the range the scan engine's ranging
    settles on for that drive, and the offset the zero measurement leaves
    (its running mean's noise). Readings over range at +/-10 V are saturated
    (NaN); below ``sign_floor_v`` they are flagged LOW_SIGNAL and SIGN_UNCERTAIN.
    """

    # The parallel chain's own error model and its one fixed gain, where the serial chains have a gain per range.
    errors: ParallelErrors      # type: ignore[assignment]
    gain: float                 # type: ignore[assignment]

    def __init__(self, profile: BoardProfile, *, errors=None, seed: int = 0, contact: ElectrodeContact | None = None):
        from appliance.drivers.channel_map import ChannelMap
        from appliance.drivers.emulated.parallel import ParallelErrors
        from appliance.drivers.frontend_parallel import parallel_ranges
        from appliance.drivers.frontend_rms import digipot_setting

        self.profile, self.contact = profile, contact
        self.at_compliance = np.zeros(0, dtype=bool)
        self.quadrature_v = np.zeros(0)
        self.rng = np.random.default_rng(seed)
        self.cmap = ChannelMap.of_profile(profile)
        self.errors = errors or ParallelErrors.drawn(np.random.default_rng(seed), self.cmap.n_channels)
        self.ranges = parallel_ranges(profile)
        assert profile.excitation.current_a is not None     # the chain's: board_profile checked it is set
        self.current_a = digipot_setting(profile, profile.excitation.current_a)[1]
        self.full_scale = np.array([r.full_scale_input_v for r in self.ranges])
        self.gain = self.ranges[0].gain

    def check(self, protocol: Protocol) -> None:
        """Refuse a protocol measuring a pair no channel reads, or for another grid."""
        g = self.profile.grid
        assert g is not None                            # a parallel profile has its grid
        if protocol.n_electrodes != g.rows * g.cols:
            raise ValueError(f"protocol for {protocol.n_electrodes} electrodes on a parallel front end built for a "
                             f"{g.rows} x {g.cols} grid")
        self._channels(protocol)

    def _channels(self, protocol: Protocol) -> tuple[np.ndarray, np.ndarray]:
        if getattr(self, "_mapped", (None,))[0] is not protocol:
            self._mapped = (protocol, *self.cmap.channels_of_protocol(protocol.readings))
        return self._mapped[1], self._mapped[2]

    def ideal(self, transfer: np.ndarray, protocol: Protocol) -> np.ndarray:
        """The in-phase differential (through two switches' on resistance); its quadrature part, which the
        demodulators pass as ``sin`` of their phase error, is kept in :attr:`quadrature_v`."""
        from appliance.drivers.emulated.parallel import SWITCH_OHM

        in_phase, self.quadrature_v = self._detected(transfer, protocol, 2 * SWITCH_OHM)
        return in_phase

    def drive_ranges(self, volts: np.ndarray, protocol: Protocol) -> np.ndarray:
        """Each reading's range: the most sensitive one keeping its whole drive under the headroom."""
        peak = np.zeros(len(protocol.drives))
        np.maximum.at(peak, protocol.drive_index, np.abs(volts))
        return self.ranges_for(peak)[protocol.drive_index]

    def readings(self, transfer: np.ndarray, protocol: Protocol) -> tuple[np.ndarray, np.ndarray]:
        from appliance.drivers.frontend_parallel import ZERO_FRAMES

        channels, signs = self._channels(protocol)
        ideal = self.ideal(transfer, protocol)
        r = self.drive_ranges(ideal, protocol)
        e, n = self.errors, len(ideal)
        lsb = np.array([rng.second_stage for rng in self.ranges])[r] / 32768
        pin = self.gain * signs * (e.channel_factor()[channels] * ideal
                                   + e.scale * (1 + e.channel_gain[channels]) * np.sin(e.phase_error_rad)
                                   * self.quadrature_v) + e.offset_v[channels]
        pin += e.input_noise_v * self.gain * self.rng.standard_normal(n)
        oversampling = self.profile.measurement.adc_oversampling
        assert oversampling is not None
        codes = np.clip(np.round(pin / lsb + e.adc_noise_lsb / np.sqrt(oversampling) * self.rng.standard_normal(n)),
                        -32768, 32767)
        zero_lsb = self.ranges[-1].second_stage / 32768
        zero_noise = np.hypot(e.adc_noise_lsb * zero_lsb, e.input_noise_v * self.gain) / np.sqrt(ZERO_FRAMES)
        zero = e.offset_v[channels] + zero_noise * self.rng.standard_normal(n)
        measured = signs * (codes * lsb - zero) / self.gain
        flags = np.zeros(n, dtype=np.int64)
        flags[self.at_compliance] |= Flag.COMPLIANCE
        saturated = (r == 0) & (np.abs(codes) / 32768 > OVER_RANGE)
        flags[saturated] |= Flag.SATURATED
        quiet = ~saturated & (np.abs(measured) < self.profile.measurement.sign_floor_v)
        flags[quiet] |= Flag.LOW_SIGNAL | Flag.SIGN_UNCERTAIN
        return np.where(saturated, np.nan, measured), flags
