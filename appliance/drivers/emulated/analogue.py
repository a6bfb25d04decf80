"""The analogue chain behind the emulated chips: current source, mat, in-amp, PGA, RMS converter.

The chain reads the emulated chips' states through small getter functions (which
drive and measuring pair the multiplexers select, the excitation current, the
AD8251 gain) and produces what the converters see: the RMS converter's output on
the ADS1115's AIN0, the phase comparator's level on a GPIO line, or the phasor at
the AD5933's VIN. It models what a driver has to respect:

- the current source clips at its compliance voltage (an open drive electrode
  leaves it at the rail and the readings near zero);
- after a drive switch the electrodes settle with time constant
  ``drive_settle_s / ln(1 / settle_accuracy)`` (the profile's wait is just enough);
- the in-amp output clips, and the AD8436 output saturates a little above its
  3 V rms range;
- the RMS converter follows its input with a first-order lag, slower for falling
  than for rising steps, so reading too early gives the previous pair's value;
- an open measuring electrode floats and picks up interference (``pickup_v``),
  which saturates any gain; per-electrode pickup also models a faulty channel;
- fixed gain errors within the parts' tolerances and white noise;
- contacts of R parallel C, when the mat has them (``sensor.contact``, an
  :class:`~appliance.drivers.emulated.electrode_interface.ElectrodeContact`): the
  differential is then a phasor, the RMS converter sees its magnitude (quadrature
  included), the phase comparator the sign of its in-phase part, and the AD5933's
  VIN the phasor itself.

Voltages are rms unless a name says peak; the sensor's transfer impedances are
ohms (``SensorModel.transfer_ohm``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from appliance.drivers.emulated.buses import InputSource
from appliance.drivers.emulated.electrode_interface import reading_phasors

INAMP_CLIP_V = 7.0          # in-amp / AD8251 output swing on +/-12 V rails, rms of the largest clean sine
RMS_SATURATION_V = 3.3      # AD8436 output ceiling
OPEN_PICKUP_V = 0.5         # a floating measuring input drifts until the in-amp saturates


def compliant_current(current_a, drive_ohm, compliance_v):
    """The current a source set to ``current_a`` delivers into ``drive_ohm``: less once it needs more
    than ``compliance_v``."""
    drive_v = current_a * np.abs(drive_ohm)
    if np.ndim(drive_v) == 0:
        return current_a * compliance_v / drive_v if drive_v > compliance_v else current_a
    return np.where(drive_v > compliance_v, current_a * compliance_v / np.maximum(drive_v, 1e-300), current_a)


class SensorModel(Protocol):
    """The mat as the chain sees it: transfer impedances between electrodes at a time, and the electrodes'
    contacts (``contact``: R parallel C, or None for the forward model's resistive contacts alone)."""

    @property
    def n_electrodes(self) -> int: ...

    def transfer_ohm(self, now_s: float) -> np.ndarray:
        """Volts at electrode m per amp into electrode l (and out through ground), shape (n, n)."""


@dataclass
class ChainState:
    """What the chips are set to, read through the getters at each change."""

    drive: tuple[int, int] | None = None         # 0-based electrodes, None while a mux is off
    measure: tuple[int, int] | None = None
    current_a: float = 0.0
    gain: float = 1.0


@dataclass
class ChainErrors:
    """Fixed errors of one board, drawn once within the parts' tolerances, and its noise."""

    scale: float = 1.0                           # current source, in-amp and RMS converter together
    gain_error: dict[float, float] = field(default_factory=dict)   # per AD8251 gain, relative
    input_noise_v: float = 0.4e-6                # input-referred, after the RMS converter's averaging
    output_ripple: float = 1e-4                  # RMS converter ripple, relative to its output

    def output_noise_v(self, gain, level_v):
        """Noise (rms) on the RMS converter's output at total ``gain`` and output ``level_v``."""
        return np.hypot(self.input_noise_v * gain, self.output_ripple * level_v)

    def gain_factor(self, pga_gain):
        """The actual over the nominal gain: the common scale error times the AD8251 step's own."""
        if np.ndim(pga_gain) == 0:
            return self.scale * (1 + self.gain_error.get(float(pga_gain), 0.0))
        errors = [self.gain_error.get(float(g), 0.0) for g in np.ravel(pga_gain)]
        return self.scale * (1 + np.reshape(errors, np.shape(pga_gain)))

    @classmethod
    def drawn(cls, rng: np.random.Generator, gains=(1, 2, 4, 8)) -> ChainErrors:
        return cls(scale=1.0 + rng.uniform(-0.003, 0.003),
                   gain_error={float(g): rng.uniform(-3e-4, 3e-4) for g in gains})


class AnalogueChain:
    """Everything between the chips' settings and the converters' inputs, in simulated time."""

    def __init__(self, clock, sensor: SensorModel, *, state: Callable[[], ChainState], inamp_gain: float,
                 compliance_v: float, drive_settle_s: float, settle_accuracy: float = 1e-4,
                 rms_rise_tau_s: float = 0.35e-3, rms_fall_tau_s: float = 0.7e-3, sign_floor_v: float = 2e-6,
                 errors: ChainErrors | None = None, seed: int = 0, frequency_hz: float = 0.0,
                 input_capacitance_f: float = 0.0):
        self.clock, self.sensor, self.read_state = clock, sensor, state
        self.contact = getattr(sensor, "contact", None)
        self.frequency_hz, self.input_capacitance_f = frequency_hz, input_capacitance_f
        self.inamp_gain, self.compliance_v, self.sign_floor_v = inamp_gain, compliance_v, sign_floor_v
        self.drive_tau_s = drive_settle_s / math.log(1 / settle_accuracy)
        self.rise_tau_s, self.fall_tau_s = rms_rise_tau_s, rms_fall_tau_s
        self.errors = errors or ChainErrors()
        self.rng = np.random.default_rng(seed)
        self.open_electrodes: set[int] = set()        # 1-based
        self.pickup_v: dict[int, float] = {}          # 1-based electrode -> interference, volts rms
        self.state = ChainState()
        self.drive_changed_at = -math.inf
        self.rms_v, self.rms_at = 0.0, clock.monotonic()
        self.input_v = 0.0                            # steady signed input-referred differential
        self.input_angle = 0.0                        # its phasor's angle from the signed real axis

    # -- state -------------------------------------------------------------------------
    def state_changed(self) -> None:
        """Called by every emulated chip after it changes: settle the old state up to now, take the new."""
        now = self.clock.monotonic()
        self._advance(now)
        new = self.read_state()
        if new.drive != self.state.drive or (new.current_a == 0) != (self.state.current_a == 0):
            self.drive_changed_at = now
        self.state = new
        self.input_angle = 0.0
        self.input_v = self.steady_input_v(now)

    def steady_input_v(self, now: float) -> float:
        """The signed differential the in-amp sees once everything has settled, volts rms."""
        s = self.state
        if s.drive is None or s.measure is None or s.current_a == 0:
            return self._pickup(s.measure)
        a, b = s.drive
        c, d = s.measure
        broken = [e for e in (a, b) if e + 1 in self.open_electrodes]
        if broken:
            # No current flows; the source drives each broken electrode's wire to its rail.
            rail = {a: self.compliance_v, b: -self.compliance_v}
            return sum(rail[e] * ((c == e) - (d == e)) for e in broken) + self._pickup(s.measure, skip=broken)
        z = self.sensor.transfer_ohm(now)
        if self.contact is not None:
            phasor = reading_phasors(z, np.array([[a, b, c, d]]), s.current_a, self.contact, self.frequency_hz,
                                     self.input_capacitance_f, self.compliance_v)[0][0]
            signed = abs(phasor) if phasor.real >= 0 else -abs(phasor)
            self.input_angle = float(np.angle(phasor / signed)) if signed else 0.0
            return self._pickup(s.measure) + signed
        current = compliant_current(s.current_a, z[a, a] - z[a, b] - z[b, a] + z[b, b], self.compliance_v)
        return self._pickup(s.measure) + current * (z[c, a] - z[c, b] - z[d, a] + z[d, b])

    def _pickup(self, measure, skip=()) -> float:
        """Interference on the measuring pair: a floating (open) input or a faulty channel."""
        if measure is None:
            return 0.0
        return sum(self.pickup_v.get(e + 1, OPEN_PICKUP_V if e + 1 in self.open_electrodes else 0.0)
                   for e in measure if e not in skip)

    # -- what the converters see ---------------------------------------------------------
    def _settling(self, t: float) -> float:
        return -math.expm1(-(t - self.drive_changed_at) / self.drive_tau_s) if t > self.drive_changed_at else 0.0

    def amplified_v(self, t: float) -> float:
        """Signed in-amp + PGA output at ``t`` (volts rms), with the drive transient and the clip."""
        gain = self.inamp_gain * self.state.gain * float(self.errors.gain_factor(self.state.gain))
        out = gain * self.input_v * self._settling(t)
        return max(-INAMP_CLIP_V, min(INAMP_CLIP_V, out))

    def _advance(self, t: float) -> None:
        """Integrate the RMS converter's lag from its last time to ``t`` under the current state."""
        if t <= self.rms_at:
            return
        target_at = lambda u: min(abs(self.amplified_v(u)), RMS_SATURATION_V)  # noqa: E731
        settled_from = max(self.rms_at, self.drive_changed_at + 40 * self.drive_tau_s)
        if t - settled_from > 40 * self.fall_tau_s:
            self.rms_v, self.rms_at = target_at(t), t
            return
        step = self.rise_tau_s / 8
        y, u = self.rms_v, self.rms_at
        while u < t:
            h = min(step, t - u)
            x = target_at(u + h / 2)
            tau = self.rise_tau_s if x > y else self.fall_tau_s
            y = x + (y - x) * math.exp(-h / tau)
            u += h
        self.rms_v, self.rms_at = y, t

    def rms_output_v(self, t: float) -> float:
        """The AD8436 output at ``t`` (no later than the next state change), with its noise."""
        self._advance(t)
        noise = math.hypot(self.errors.input_noise_v * self.inamp_gain * self.state.gain,
                           self.errors.output_ripple * self.rms_v)
        return max(0.0, self.rms_v + noise * self.rng.standard_normal())

    def pin_volts(self, pin: str, t: float) -> float:
        """ADS1115 inputs: AIN0 carries the RMS converter's output; the others are grounded."""
        return self.rms_output_v(t) if pin == "AIN0" else 0.0

    def vin_phasor(self, t: float, vin_gain: float) -> complex:
        """The AD5933's VIN: the amplified differential through ``vin_gain``, volts peak, at its phase."""
        self._advance(t)
        noise = self.errors.input_noise_v * self.inamp_gain * self.state.gain * self.rng.standard_normal()
        return vin_gain * math.sqrt(2) * (self.amplified_v(t) + noise) * complex(math.cos(self.input_angle),
                                                                               math.sin(self.input_angle))

    def phase_source(self) -> InputSource:
        """The phase comparator's output: 1 while the reading is in phase with the drive."""
        return _PhaseComparator(self)


class _PhaseComparator(InputSource):
    def __init__(self, chain: AnalogueChain):
        self.chain = chain

    def level(self, now: float) -> int:
        value = self.chain.input_v * self.chain._settling(now)
        if abs(value) < self.chain.sign_floor_v / 2:
            return int(self.chain.rng.integers(0, 2))
        return int(value > 0)

    def next_edge(self, after: float, edge: str) -> float | None:
        return None
