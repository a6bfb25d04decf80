"""The analogue chain applied to a whole frame at once: the virtual bed's fast path.

The emulated board runs the chips one transfer at a time, which is right for
testing drivers and too slow for a bed-size mat at a frame a second. This
module gives the same readings a settled scan would: the current source's
compliance, each reading auto-ranged to the largest gain that does not
saturate (the profile's range ladder), the chain's gain errors
(:class:`~appliance.drivers.emulated.analogue.ChainErrors`), its noise, the
converter's quantisation at that range, saturation at the least sensitive
range, and the sign lost below the phase comparator's floor.

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

import numpy as np

from appliance.core.protocols import Protocol
from appliance.drivers.emulated.analogue import ChainErrors, compliant_current
from appliance.drivers.frontend import OVER_RANGE
from appliance.drivers.profile import BoardProfile
from appliance.drivers.scan import Flag


class FrameChain:
    """Readings of a whole frame from transfer impedances, as the profile's front end would take them."""

    def __init__(self, profile: BoardProfile, *, errors: ChainErrors | None = None, seed: int = 0):
        self.profile = profile
        self.rng = np.random.default_rng(seed)
        self.errors = errors or ChainErrors.drawn(np.random.default_rng(seed))
        if profile.chain == "rms":
            from appliance.drivers.frontend_rms import digipot_setting, rms_ranges

            self.ranges = rms_ranges(profile)
            self.current_a = digipot_setting(profile, profile.excitation.current_a)[1]
        else:
            from appliance.drivers.frontend_ad5933 import ACTUAL_VPP, ad5933_ranges

            self.ranges = ad5933_ranges(profile)
            x = profile.excitation
            self.current_a = ACTUAL_VPP[x.output_range_vpp] / (2 * np.sqrt(2)) * x.transconductance_a_per_v
        self.full_scale = np.array([r.full_scale_input_v for r in self.ranges])
        self.gain = np.array([r.gain for r in self.ranges])

    def ideal(self, transfer: np.ndarray, protocol: Protocol) -> np.ndarray:
        """V(meas+) - V(meas-) at the set current (less where the source reaches compliance), volts rms."""
        a, b, c, d = (protocol.readings - 1).T
        z = transfer
        current = compliant_current(self.current_a, z[a, a] - z[a, b] - z[b, a] + z[b, b],
                                    self.profile.excitation.compliance_v)
        return current * (z[c, a] - z[c, b] - z[d, a] + z[d, b])

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
        # One DFT count, referred to the RMS level after the in-amp and AD8251.
        return 1.0 / (m.dft_counts_per_volt * m.vin_gain * np.sqrt(2) * pga)
