"""Register-level emulator of the AD5933 impedance converter, fed by the analogue chain outside it.

What it models, and the figures it uses:

- **Protocol.** The datasheet's pointer protocol is the only read path:
  ``[0xB0, reg]`` sets the pointer; a receive byte returns the register at the
  pointer (without moving it [recall: verify]); ``[0xA1, n]`` joined to a read
  of n bytes reads n registers from the pointer up; ``[0xA0, n, data...]``
  writes n registers from the pointer up; ``[reg, value]`` writes one register.
  SMBus read-byte-data (``[reg]`` joined to a read) is not documented for this
  chip, so it raises :class:`EmulatorViolation` unless built with ``lenient=True``.
  Reserved bits, reserved function codes, the reserved settling multiplier and
  registers that do not exist raise it too. Writes to the read-only registers
  (status, temperature, real, imaginary) are ignored, as by the chip, with a
  note in :attr:`warnings`.
- **Power-on state.** Control = 0xA0 0x00 (power-down, 2 V p-p, PGA x5); the
  other registers read 0 [recall: verify]; the pointer is unset.
- **States.** power-down -> standby -> initialised (excitation on at the start
  frequency) -> sweeping. Start sweep (from initialised), Increment and Repeat
  begin a point: status bit 1 (valid data) is clear until (settling cycles x
  multiplier) / f + 1024 / (MCLK / 16) seconds of clock time after the command;
  the real and imaginary registers hold the previous point until then. Bit 2
  (sweep complete) comes with the last point. A measuring command in any other
  state does nothing (the chip is not exciting; there is nothing to measure) and
  is noted in :attr:`warnings`. The reset bit (0x81 bit 4) stops a sweep, back to
  standby, and clears itself [recall: verify]. The external-clock bit raises
  EmulatorViolation: only the internal oscillator is modelled. Measure
  temperature (0x9) sets bit 0 after 800 us and leaves the state alone [recall: verify].
- **DFT codes.** ``vin(t)`` is the phasor (volts peak, relative to the
  excitation) the receive stage presents to the PGA (on the real chip: the
  current into VIN times the feedback resistor). The emulator multiplies it by
  the PGA gain, limits it where the ADC clips, and returns
  ``R + jI = COUNTS_PER_VOLT * v * exp(j * SYSTEM_PHASE)`` plus Gaussian noise,
  rounded and saturated to int16, taken at the instant the DFT completes.
  ``COUNTS_PER_VOLT`` (9790) and the system phase (114.35 degrees) come from the
  datasheet's gain-factor example (Rev. E, p. 17: real -3996, imaginary 8830 for
  2 V p-p, 0.99 V peak actual, through 200 kOhm into 200 kOhm, PGA x1, 30 kHz); a
  real part's phase varies with frequency, this one's does not. The ADC samples
  around VDD/2 with a 0..VDD range, 1.65 V peak at 3.3 V; ``ADC_CLIP_V_PEAK`` =
  1.5 V leaves the margin of its buffers [recall: verify]. A clipped sine's
  fundamental (what a DFT at the excitation frequency sees) is modelled exactly.
"""

from __future__ import annotations

import cmath
import math
import random
from collections.abc import Callable

from appliance.drivers.emulated.buses import EmulatorViolation, I2CChipEmulator, notify
from appliance.drivers.emulated.clock import SimulatedClock

COUNTS_PER_VOLT = 9790.0
SYSTEM_PHASE_DEG = 114.35
ADC_CLIP_V_PEAK = 1.5
OUTPUT_VPP = {0b00: 1.98, 0b01: 0.198, 0b10: 0.383, 0b11: 0.970}
"""Excitation amplitude per range code at 3.3 V (the Linux driver's figures for the nominal 2, 0.2, 0.4, 1 V p-p)."""
DFT_SAMPLES = 1024
TEMPERATURE_TIME_S = 800e-6
STATUS_DONT_CARE = 0x70
"""Upper status bits are undefined; users report reads such as 0x70, so drivers must mask."""

POWER_DOWN, STANDBY, INITIALISED, SWEEPING = "power-down", "standby", "initialised", "sweeping"
VALID_TEMPERATURE, VALID_DATA, SWEEP_COMPLETE = 0x01, 0x02, 0x04
SET_POINTER, BLOCK_WRITE, BLOCK_READ = 0xB0, 0xA0, 0xA1
CONTROL_HB, CONTROL_LB, STATUS, SETTLING_HB = 0x80, 0x81, 0x8F, 0x8A
RESET_BIT, EXTERNAL_CLOCK_BIT = 0x10, 0x08

RESERVED_BITS = {0x80: 0x08, 0x81: 0xE7, 0x82: 0, 0x83: 0, 0x84: 0, 0x85: 0, 0x86: 0, 0x87: 0,
                 0x88: 0xFE, 0x89: 0, 0x8A: 0xF8, 0x8B: 0}
"""The writable registers and the bits of each that must be written 0."""
READ_ONLY = (0x8F, 0x92, 0x93, 0x94, 0x95, 0x96, 0x97)
FUNCTIONS = {0x0: "no operation", 0x1: "initialise", 0x2: "start sweep", 0x3: "increment", 0x4: "repeat",
             0x9: "measure temperature", 0xA: "power-down", 0xB: "standby"}
SETTLING_MULTIPLIERS = {0b00: 1, 0b01: 2, 0b11: 4}


class EmulatedAD5933(I2CChipEmulator):
    """An AD5933 at 0x0D whose receive stage sees ``vin(now)``; the module docstring gives the model."""

    name = "AD5933"
    address = 0x0D
    pointer: int | None                 # the register the pointer protocol reads next

    def __init__(self, clock: SimulatedClock, vin: Callable[[float], complex] | None = None, *,
                 mclk_hz: float = 16.776e6, temperature_c: Callable[[float], float] | None = None,
                 noise_counts: float = 0.0, seed: int = 0, lenient: bool = False):
        self.clock = clock
        self.vin = vin if vin is not None else (lambda now: 0j)
        self.temperature_source = temperature_c if temperature_c is not None else (lambda now: 25.0)
        self.mclk_hz = mclk_hz
        self.noise_counts = noise_counts
        self.lenient = lenient
        self._rng = random.Random(seed)
        self.listeners: list[Callable[[], None]] = []
        self.warnings: list[str] = []
        self._power_on()

    def reset(self) -> None:
        """Return to the power-on state (a power cycle)."""
        self._notifying(self._power_on)

    @property
    def output_frequency_hz(self) -> float | None:
        """The excitation frequency, or None unless exciting (initialised or sweeping)."""
        if self.mode not in (INITIALISED, SWEEPING):
            return None
        return (self._start_code + self._index * self._increment_code) * (self.mclk_hz / 4) / 2**27

    @property
    def output_vpp(self) -> float:
        """The excitation amplitude the range bits select (also while not exciting)."""
        return OUTPUT_VPP[self.registers[CONTROL_HB] >> 1 & 0b11]

    @property
    def pga_gain(self) -> int:
        return 1 if self.registers[CONTROL_HB] & 1 else 5

    def write(self, data: bytes) -> None:
        self._advance()
        self._notifying(lambda: self._write(bytes(data)))

    def read(self, n: int) -> bytes:
        self._advance()
        if n != 1:
            raise EmulatorViolation(f"{self.name}: a plain read is a receive byte (1 byte), not {n}; "
                                    f"read several registers with a block read [0xA1, n]")
        return bytes([self._register(self._require_pointer())])

    def write_read(self, data: bytes, n: int) -> bytes:
        self._advance()
        data = bytes(data)
        if len(data) == 2 and data[0] == BLOCK_READ:
            if data[1] != n:
                raise EmulatorViolation(f"{self.name}: block read announced {data[1]} bytes but read {n}")
            first = self._require_pointer()
        elif len(data) == 1 and self.lenient:
            first = self.pointer = self._require_register(data[0])
        elif len(data) == 1:
            raise EmulatorViolation(f"{self.name}: SMBus read-byte-data of 0x{data[0]:02X} is not a documented "
                                    f"read; set the pointer with [0xB0, reg], then receive byte or [0xA1, n]")
        else:
            raise EmulatorViolation(f"{self.name}: a joined read must start with [0xA1, n], not {data.hex()}")
        return bytes(self._register(first + offset) for offset in range(n))

    def _power_on(self) -> None:
        self.registers = dict.fromkeys((*RESERVED_BITS, *READ_ONLY), 0)
        self.registers[CONTROL_HB] = 0xA0
        self.pointer = None
        self.mode = POWER_DOWN
        self._status = 0
        self._start_code = self._increment_code = self._increments = self._index = 0
        self._data_due_s: float | None = None
        self._temperature_due_s: float | None = None

    def _notifying(self, action: Callable[[], None]) -> None:
        """Run ``action``; call the listeners if the excitation's frequency or amplitude changed."""
        before = (self.output_frequency_hz, self.output_vpp)
        action()
        if (self.output_frequency_hz, self.output_vpp) != before:
            notify(self.listeners)

    def _write(self, data: bytes) -> None:
        if len(data) < 2:
            raise EmulatorViolation(f"{self.name}: a write needs a register or command byte and data, got {data.hex()}")
        if data[0] == SET_POINTER and len(data) == 2:
            self.pointer = self._require_register(data[1])
        elif data[0] == BLOCK_WRITE:
            if len(data) != 2 + data[1]:
                raise EmulatorViolation(f"{self.name}: block write announced {data[1]} bytes, sent {len(data) - 2}")
            first = self._require_pointer()
            for offset, value in enumerate(data[2:]):
                self._write_register(first + offset, value)
        elif data[0] == BLOCK_READ:
            raise EmulatorViolation(f"{self.name}: block read [0xA1, n] must be joined to its read "
                                    f"by a repeated start")
        elif len(data) == 2:
            self._write_register(data[0], data[1])
        else:
            raise EmulatorViolation(f"{self.name}: registers are written one byte at a time, "
                                    f"[reg, value]; got {data.hex()}")

    def _write_register(self, register: int, value: int) -> None:
        if register in READ_ONLY:
            self.warnings.append(f"write of 0x{value:02X} to read-only register 0x{register:02X} ignored")
            return
        if register not in RESERVED_BITS:
            raise EmulatorViolation(f"{self.name}: there is no register 0x{register:02X} to write")
        if value & RESERVED_BITS[register]:
            raise EmulatorViolation(f"{self.name}: 0x{value:02X} written to register 0x{register:02X} sets "
                                    f"reserved bits 0x{value & RESERVED_BITS[register]:02X}")
        if register == SETTLING_HB and value >> 1 & 0b11 not in SETTLING_MULTIPLIERS:
            raise EmulatorViolation(f"{self.name}: settling multiplier code 0b10 is reserved")
        if register == CONTROL_HB:
            self._control(value)
        elif register == CONTROL_LB:
            if value & EXTERNAL_CLOCK_BIT:
                raise EmulatorViolation(f"{self.name}: external clock selected; no clock drives MCLK here")
            self.registers[CONTROL_LB] = value & ~RESET_BIT
            if value & RESET_BIT:
                self._stop(STANDBY if self.mode in (INITIALISED, SWEEPING) else self.mode)
        else:
            self.registers[register] = value

    def _control(self, value: int) -> None:
        """A write of the control high byte: latch range and PGA, then run the function code."""
        function = value >> 4
        if function not in FUNCTIONS:
            raise EmulatorViolation(f"{self.name}: function code 0x{function:X} is reserved")
        self.registers[CONTROL_HB] = value
        if function in (0xA, 0xB):
            self._stop(POWER_DOWN if function == 0xA else STANDBY)
        elif function == 0x1:
            self._stop(INITIALISED)
            self._start_code = self._value(0x82, 3)
            self._increment_code = self._value(0x85, 3)
            self._increments = self._value(0x88, 2)
        elif function == 0x9:
            self._status &= ~VALID_TEMPERATURE
            self._temperature_due_s = self.clock.monotonic() + TEMPERATURE_TIME_S
        elif function in (0x2, 0x3, 0x4):
            self._measure_command(function)

    def _measure_command(self, function: int) -> None:
        allowed = (INITIALISED, SWEEPING) if function == 0x2 else (SWEEPING,)
        if self.mode not in allowed:
            self.warnings.append(f"{FUNCTIONS[function]} ignored in {self.mode}")
            return
        if function == 0x2:
            self.mode, self._index = SWEEPING, 0
            self._status &= ~SWEEP_COMPLETE
        elif function == 0x3 and self._index < self._increments:
            self._index += 1
        elif function == 0x3:
            self.warnings.append("increment past the last point repeats it")
        settling_hb = self.registers[SETTLING_HB]
        cycles = ((settling_hb & 1) << 8 | self.registers[0x8B]) * SETTLING_MULTIPLIERS[settling_hb >> 1 & 0b11]
        self._status &= ~VALID_DATA
        frequency_hz = self.output_frequency_hz
        assert frequency_hz is not None         # initialised or sweeping
        self._data_due_s = (self.clock.monotonic() + cycles / frequency_hz
                            + DFT_SAMPLES / (self.mclk_hz / 16))

    def _stop(self, mode: str) -> None:
        """Enter ``mode``, abandoning any sweep and point in progress."""
        self.mode, self._index, self._data_due_s = mode, 0, None
        self._status &= ~(VALID_DATA | SWEEP_COMPLETE)

    def _advance(self) -> None:
        """Finish the conversions whose time has come, at the instant each completed."""
        now = self.clock.monotonic()
        if self._data_due_s is not None and now >= self._data_due_s:
            real, imag = self._dft_codes(self._data_due_s)
            self._store(0x94, real & 0xFFFF, 2)
            self._store(0x96, imag & 0xFFFF, 2)
            self._data_due_s = None
            self._status |= VALID_DATA | (SWEEP_COMPLETE if self._index >= self._increments else 0)
        if self._temperature_due_s is not None and now >= self._temperature_due_s:
            self._store(0x92, round(self.temperature_source(self._temperature_due_s) * 32) & 0x3FFF, 2)
            self._temperature_due_s = None
            self._status |= VALID_TEMPERATURE

    def _dft_codes(self, when_s: float) -> tuple[int, int]:
        v = complex(self.vin(when_s)) * self.pga_gain
        peak_v = abs(v)
        if peak_v > ADC_CLIP_V_PEAK:
            v *= _clipped_fundamental_v(peak_v, ADC_CLIP_V_PEAK) / peak_v
        z = COUNTS_PER_VOLT * v * cmath.exp(1j * math.radians(SYSTEM_PHASE_DEG))
        real, imag = (max(-32768, min(32767, round(part + self._rng.gauss(0.0, self.noise_counts))))
                      for part in (z.real, z.imag))
        return real, imag

    def _value(self, first: int, n_bytes: int) -> int:
        return int.from_bytes(bytes(self.registers[first + i] for i in range(n_bytes)), "big")

    def _store(self, first: int, value: int, n_bytes: int) -> None:
        for offset, byte in enumerate(value.to_bytes(n_bytes, "big")):
            self.registers[first + offset] = byte

    def _register(self, register: int) -> int:
        self._require_register(register)
        return self._status | STATUS_DONT_CARE if register == STATUS else self.registers[register]

    def _require_register(self, register: int) -> int:
        if register not in self.registers:
            raise EmulatorViolation(f"{self.name}: there is no register 0x{register:02X}")
        return register

    def _require_pointer(self) -> int:
        if self.pointer is None:
            raise EmulatorViolation(f"{self.name}: read before the address pointer was set with [0xB0, reg]")
        return self.pointer


def _clipped_fundamental_v(peak_v: float, clip_v: float) -> float:
    """Amplitude of the fundamental of a sine of ``peak_v`` clipped at +-``clip_v`` (at most 4/pi * clip_v)."""
    angle = math.asin(clip_v / peak_v)
    return 2 * peak_v / math.pi * (angle + math.sin(angle) * math.cos(angle))
