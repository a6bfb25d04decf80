"""The parallel front end's analogue side: switch matrix, current source, mat, and a demodulating channel per pair.

Every horizontally adjacent pair has its own chain: in-amp (fixed gain) ->
synchronous demodulator switched by the excitation's square wave -> two-pole
low-pass with gain -> an AD7606 input. :class:`ParallelChain` gives, for any
time, what each AD7606 input sees; it models what the drivers must respect:

- the current source delivers its set current unless the drive pair (two
  ADG1414 on resistances included) needs more than its compliance voltage;
- each channel's low-pass output follows its target with the step response of
  two equal real poles (critically damped), so a conversion taken too soon
  after a drive change reads part of the previous drive's level;
- the demodulator keeps the in-phase part of the differential voltage and
  rejects the quadrature part (from the electrodes' contact capacitance)
  except for ``sin`` of the reference's phase error; its mean output per volt
  rms of an in-phase sine is 2 sqrt(2) / pi;
- the in-amp clips a large differential (a floating open electrode's pickup,
  a broken drive electrode at the source's rail), and the low-pass output
  stops at its rails;
- contacts of R parallel C, when the mat has them (``sensor.contact``): each
  channel's differential is then a phasor, whose quadrature part joins the
  channel's own leak;
- fixed per-channel gain and offset errors (the offsets sit after the
  demodulator, which turns the in-amp's own offset into a square wave the
  low-pass removes), the current source's scale error, and white noise.

Voltages are rms before the demodulator and plain volts after it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from appliance.drivers.channel_map import CHANNELS_PER_ADC, ChannelMap
from appliance.drivers.emulated.analogue import INAMP_CLIP_V, OPEN_PICKUP_V, SensorModel, compliant_current
from appliance.drivers.emulated.electrode_interface import reading_phasors

DEMODULATOR_GAIN = 2 * math.sqrt(2) / math.pi
LOWPASS_RAIL_V = 11.0          # the low-pass op-amp's output swing on +/-12 V rails
SWITCH_OHM = 9.5               # ADG1414 on resistance at +/-15 V, one in each current path
POLE_RATIO = math.sqrt(math.sqrt(2) - 1)
"""The -3 dB frequency of two equal real poles is this fraction of the poles' frequency (0.6436)."""


def pole_time_constant_s(lowpass_hz: float) -> float:
    """The time constant of each of the two equal poles of a low-pass whose -3 dB point is ``lowpass_hz``."""
    return POLE_RATIO / (2 * math.pi * lowpass_hz)


def settle_time_s(lowpass_hz: float, accuracy: float) -> float:
    """How long a critically damped low-pass takes to come within ``accuracy`` of a step: (1 + x) e^-x = accuracy."""
    x = -math.log(accuracy)
    for _ in range(50):
        x = -math.log(accuracy) + math.log1p(x)
    return x * pole_time_constant_s(lowpass_hz)


@dataclass
class ParallelErrors:
    """Fixed errors of one parallel board, drawn once within its parts' tolerances, and its noise."""

    scale: float = 1.0                              # current source
    channel_gain: np.ndarray = field(default_factory=lambda: np.zeros(0))   # relative, per channel
    offset_v: np.ndarray = field(default_factory=lambda: np.zeros(0))       # at the ADC input, per channel
    quadrature: np.ndarray = field(default_factory=lambda: np.zeros(0))     # quadrature / in-phase, per channel
    phase_error_rad: float = 0.0                    # demodulator reference against the current
    input_noise_v: float = 0.4e-6                   # input-referred, per conversion, after the low-pass
    adc_noise_lsb: float = 0.5                      # AD7606 transition noise

    @classmethod
    def drawn(cls, rng: np.random.Generator, n_channels: int) -> ParallelErrors:
        return cls(scale=1.0 + rng.uniform(-0.002, 0.002),
                   channel_gain=rng.uniform(-0.002, 0.002, n_channels),
                   offset_v=rng.uniform(-0.5e-3, 0.5e-3, n_channels),
                   quadrature=rng.uniform(-0.1, 0.1, n_channels),
                   phase_error_rad=math.radians(rng.uniform(-0.5, 0.5)))

    def channel_factor(self, phase_rad: float | None = None) -> np.ndarray:
        """What each channel's demodulated output is per volt of in-phase input, relative to nominal."""
        phase = self.phase_error_rad if phase_rad is None else phase_rad
        return self.scale * (1 + self.channel_gain) * (math.cos(phase) + self.quadrature * math.sin(phase))


@dataclass
class DriveState:
    """What the chips are set to: the drive pair (0-based, None while a bus is empty) and the current."""

    drive: tuple[int, int] | None = None
    current_a: float = 0.0


class ParallelChain:
    """Everything between the chips' settings and the AD7606 inputs, in simulated time."""

    def __init__(self, clock, sensor: SensorModel, cmap: ChannelMap, *, state: Callable[[], DriveState],
                 inamp_gain: float, lowpass_gain: float, lowpass_hz: float, compliance_v: float,
                 errors: ParallelErrors, seed: int = 0, frequency_hz: float = 0.0, input_capacitance_f: float = 0.0):
        self.clock, self.sensor, self.cmap, self.read_state = clock, sensor, cmap, state
        self.contact = getattr(sensor, "contact", None)
        self.frequency_hz, self.input_capacitance_f = frequency_hz, input_capacitance_f
        self.inamp_gain, self.lowpass_gain, self.compliance_v = inamp_gain, lowpass_gain, compliance_v
        self.tau = pole_time_constant_s(lowpass_hz)
        self.errors = errors
        self.rng = np.random.default_rng(seed)
        pairs = np.array([cmap.pair_of(c) for c in range(cmap.n_channels)]) - 1
        self.first, self.second = pairs[:, 0], pairs[:, 1]
        self.before_change: list[Callable[[float], None]] = []
        self.open_electrodes: set[int] = set()        # 1-based
        self.pickup_v: dict[int, float] = {}          # 1-based electrode -> interference, volts rms
        n = cmap.n_channels
        self.y, self.slope, self.x = np.zeros(n), np.zeros(n), np.zeros(n)
        self.quadrature_v = np.zeros(n)               # the contacts' quadrature part of each differential
        self.since = clock.monotonic()
        self.state = DriveState()
        self._cache: tuple[float | None, np.ndarray | None] = (None, None)

    # -- state -------------------------------------------------------------------------
    def power_on(self) -> None:
        """Take the chips' state as long settled (the board has been powered a while before it is opened)."""
        self.state = self.read_state()
        self.since = self.clock.monotonic()
        self.x = self.target_v(self.since)
        self.y, self.slope = self.x.copy(), np.zeros_like(self.x)

    def state_changed(self) -> None:
        """Called by every emulated chip after a change: the converters sample what they owe first, then the
        low-pass keeps its output and slope and heads for the new target."""
        now = self.clock.monotonic()
        for listener in list(self.before_change):
            listener(now)
        self.y, self.slope = self._response(now)
        self.since = now
        self.state = self.read_state()
        self.x = self.target_v(now)
        self._cache = (None, None)

    def _response(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Output and slope at ``t`` of two equal poles heading from (y, slope) at ``since`` to the target."""
        dt = max(0.0, t - self.since)
        error = self.y - self.x
        b = self.slope + error / self.tau
        decay = math.exp(-dt / self.tau)
        return self.x + (error + b * dt) * decay, decay * (self.slope - b * dt / self.tau)

    def differential_v(self, now: float) -> np.ndarray:
        """The in-phase differential each channel's in-amp sees once settled, volts rms (its quadrature part
        from the contacts in :attr:`quadrature_v`)."""
        s, first, second = self.state, self.first, self.second
        v = np.zeros(self.cmap.n_channels)
        self.quadrature_v = np.zeros(self.cmap.n_channels)
        broken: list[int] = []
        if s.drive is not None and s.current_a > 0:
            a, b = s.drive
            broken = [e for e in (a, b) if e + 1 in self.open_electrodes]
            if broken:
                # No current flows; the source drives each broken electrode's wire to its rail.
                for e, rail in ((a, self.compliance_v), (b, -self.compliance_v)):
                    if e in broken:
                        v += rail * ((first == e).astype(float) - (second == e))
            elif self.contact is not None:
                readings = np.column_stack([np.full_like(first, a), np.full_like(first, b), first, second])
                phasors = reading_phasors(self.sensor.transfer_ohm(now), readings, s.current_a, self.contact,
                                          self.frequency_hz, self.input_capacitance_f, self.compliance_v,
                                          2 * SWITCH_OHM)[0]
                v, self.quadrature_v = phasors.real, phasors.imag
            else:
                z = self.sensor.transfer_ohm(now)
                current = compliant_current(s.current_a, z[a, a] - z[a, b] - z[b, a] + z[b, b] + 2 * SWITCH_OHM,
                                            self.compliance_v)
                v = current * (z[first, a] - z[first, b] - z[second, a] + z[second, b])
        pickup = np.zeros(self.sensor.n_electrodes)
        for e in self.open_electrodes:
            pickup[e - 1] = OPEN_PICKUP_V
        for e, volts in self.pickup_v.items():
            pickup[e - 1] = volts
        pickup[broken] = 0.0
        return v + pickup[first] + pickup[second]

    def target_v(self, now: float) -> np.ndarray:
        """Each low-pass output once settled (volts, before its rails)."""
        v = self.differential_v(now)
        e = self.errors
        quadrature = e.quadrature * v + self.quadrature_v
        amplitude = self.inamp_gain * np.hypot(v, quadrature)
        clip = np.minimum(1.0, INAMP_CLIP_V / np.maximum(amplitude, 1e-300))
        demodulated = DEMODULATOR_GAIN * self.inamp_gain * clip * (v * math.cos(e.phase_error_rad)
                                                                   + quadrature * math.sin(e.phase_error_rad))
        return e.scale * (1 + e.channel_gain) * self.lowpass_gain * demodulated + e.offset_v

    # -- what the converters see ---------------------------------------------------------
    def outputs_v(self, t: float) -> np.ndarray:
        """Every low-pass output at ``t`` (no later than the next state change), with its noise, volts."""
        y, _ = self._response(t)
        gain = self.inamp_gain * DEMODULATOR_GAIN * self.lowpass_gain
        noise = self.errors.input_noise_v * gain * self.rng.standard_normal(len(y))
        return np.clip(y + noise, -LOWPASS_RAIL_V, LOWPASS_RAIL_V)

    def adc_inputs(self, t: float) -> np.ndarray:
        """The eight inputs of every AD7606 at ``t``, shape (n_adcs, 8); inputs with no channel read 0 V."""
        cached_t, out = self._cache
        if cached_t != t or out is None:
            out = np.zeros((self.cmap.n_adcs, CHANNELS_PER_ADC))
            index = self.cmap.adc_index
            out[index[:, 0], index[:, 1]] = self.outputs_v(t)
            self._cache = (t, out)
        return out
