"""Driver of the AD5933 impedance converter (I2C address 0x0D): excitation, 12-bit ADC and 1024-point DFT on chip.

The chip excites a load at one programmed frequency and returns the DFT of what
comes back as real and imaginary 16-bit codes. The driver returns the raw codes;
turning them into an impedance (gain factor, system phase) is the caller's calibration.

- Registers are written one byte at a time (``[reg, value]``) and read only by
  the datasheet's pointer protocol (``[0xB0, reg]``, then a receive byte or a
  block read ``[0xA1, n]`` joined to its read), never by SMBus read-byte-data,
  which the datasheet does not document for this chip.
- The output-range and PGA bits share the control register with the function
  code, so every command write must repeat them: the driver keeps a shadow.
- Every wait (load settling, polling for valid data) goes through the injected
  :class:`~appliance.drivers.bus.Clock`, so under emulation it is simulated time.

>>> from appliance.drivers.emulated.buses import EmulatedI2CBus
>>> from appliance.drivers.emulated.clock import SimulatedClock
>>> from appliance.drivers.emulated.ad5933 import EmulatedAD5933
>>> clock = SimulatedClock()
>>> bus = EmulatedI2CBus(1, clock)
>>> bus.attach(EmulatedAD5933(clock, lambda now: 0.5))
>>> chip = AD5933(bus, clock)
>>> chip.configure(50_000, settling_cycles=15, output_range_vpp=2.0, pga_gain=1)
>>> chip.start()
>>> chip.measure()
(-2018+4460j)
"""

from __future__ import annotations

from types import MappingProxyType

from appliance.drivers.bus import Clock, I2CBus
from appliance.errors import ChipNotResponding, ChipReadbackMismatch

REG_CONTROL_HB = 0x80
REG_CONTROL_LB = 0x81
REG_START_FREQUENCY = 0x82
REG_FREQUENCY_INCREMENT = 0x85
REG_INCREMENTS = 0x88
REG_SETTLING_CYCLES = 0x8A
REG_STATUS = 0x8F
REG_TEMPERATURE = 0x92
REG_REAL = 0x94

CMD_BLOCK_READ, CMD_SET_POINTER = 0xA1, 0xB0

FN_NOP = 0x0
FN_INITIALISE = 0x1
FN_START_SWEEP = 0x2
FN_INCREMENT = 0x3
FN_REPEAT = 0x4
FN_MEASURE_TEMPERATURE = 0x9
FN_POWER_DOWN = 0xA
FN_STANDBY = 0xB

CONTROL_LB_RESET = 0x10

STATUS_VALID_TEMPERATURE, STATUS_VALID_DATA, STATUS_SWEEP_COMPLETE = 0x01, 0x02, 0x04
STATUS_MASK = 0x07  # the upper bits are undefined

DFT_SAMPLES = 1024
TEMPERATURE_TIME_S = 800e-6
TIMEOUT_FACTOR, TIMEOUT_SLACK_S = 1.5, 5e-3  # a wait for the chip lasts 1.5 times its nominal time + 5 ms

INT16_MIN, INT16_MAX = -32768, 32767
CODE_LIMIT = 14_000
"""DFT magnitude at which a reading counts as saturated.

A full-scale sine at the ADC (about 1.5 V peak) gives about 14700 counts on the
datasheet's scale (magnitude 9692 for 0.99 V peak: 2 V p-p through 200 kOhm into
a 200 kOhm feedback resistor, PGA x1); a clipped input gives more than that
while the load it reports on is wrong. The limit is about 95 % of it, leaving
room for the DC offset and gain tolerance of a real part.
"""


class AD5933:
    """One AD5933 on an I2C bus; returns raw DFT codes at one frequency, point by point.

    ``init_settle_s`` is the wait after *Initialise with start frequency*. The
    Linux driver waits 100 ms there because it cannot know the load. Here the
    *Start sweep* command itself waits the programmed settling cycles before
    the DFT, and those are chosen to cover the load's settling, so this wait only
    covers the excitation coming out of standby: 2 ms by default. A front end
    that AC-couples the excitation needs several of its coupling time constants.
    ``poll_interval_s`` is the pause between reads of the status register.
    """

    OUTPUT_RANGES_VPP = MappingProxyType({2.0: 0b00, 0.2: 0b01, 0.4: 0b10, 1.0: 0b11})
    PGA_GAINS = (1, 5)
    CODE_LIMIT = CODE_LIMIT
    MIN_FREQUENCY_HZ = 1_000.0
    MAX_FREQUENCY_HZ = 100_000.0
    MAX_INCREMENTS = 511
    MAX_SETTLING_CYCLES = 2044

    def __init__(self, i2c: I2CBus, clock: Clock, *, address: int = 0x0D, mclk_hz: float = 16.776e6,
                 init_settle_s: float = 2e-3, poll_interval_s: float = 0.2e-3):
        self._i2c = i2c
        self._clock = clock
        self.address = address
        self.mclk_hz = mclk_hz
        self.init_settle_s = init_settle_s
        self.poll_interval_s = poll_interval_s
        self.name = f"AD5933 at 0x{address:02X}"
        self._range_bits = 0b00  # the power-on state: 2 V p-p, PGA x5
        self._pga_bit = 0
        self._start_code: int | None = None
        self._settling_cycles = 0
        self._running = False
        self._fresh_point = False

    def frequency_code(self, frequency_hz: float) -> int:
        """The 24-bit code of ``frequency_hz``: round(f * 2**27 / (MCLK / 4))."""
        if not self.MIN_FREQUENCY_HZ <= frequency_hz <= self.MAX_FREQUENCY_HZ:
            raise ValueError(f"{self.name}: frequency {frequency_hz!r} Hz is outside "
                             f"{self.MIN_FREQUENCY_HZ:g}..{self.MAX_FREQUENCY_HZ:g} Hz")
        return self._code(frequency_hz, "frequency")

    def configure(self, frequency_hz: float, *, settling_cycles: int, output_range_vpp: float, pga_gain: int,
                  increments: int = 0, increment_hz: float = 0.0) -> None:
        """Program a sweep from ``frequency_hz`` and leave the chip in standby with the new range and PGA.

        Settling cycles beyond 511 use the chip's x2 or x4 multiplier, rounding
        the count up so the load settles at least as long as asked (2044 at most).
        Raises :class:`ChipReadbackMismatch` if the start frequency reads back wrong.
        """
        start_code = self.frequency_code(frequency_hz)
        if not isinstance(increments, int) or not 0 <= increments <= self.MAX_INCREMENTS:
            raise ValueError(f"{self.name}: increments {increments!r} is outside 0..{self.MAX_INCREMENTS}")
        if not increment_hz >= 0:
            raise ValueError(f"{self.name}: increment {increment_hz!r} Hz must be at least 0")
        stop_hz = frequency_hz + increments * increment_hz
        if stop_hz > self.MAX_FREQUENCY_HZ:
            raise ValueError(f"{self.name}: sweep ends at {stop_hz:g} Hz, beyond {self.MAX_FREQUENCY_HZ:g} Hz")
        increment_code = self._code(increment_hz, "frequency increment")
        settling_word, settling_cycles = self._settling_word(settling_cycles)
        range_bits, pga_bit = self._range_bits_of(output_range_vpp), self._pga_bit_of(pga_gain)
        self._write_register(REG_START_FREQUENCY, start_code, 3)
        self._write_register(REG_FREQUENCY_INCREMENT, increment_code, 3)
        self._write_register(REG_INCREMENTS, increments, 2)
        self._write_register(REG_SETTLING_CYCLES, settling_word, 2)
        self._range_bits, self._pga_bit = range_bits, pga_bit
        self._command(FN_STANDBY)
        self._running = self._fresh_point = False
        readback = int.from_bytes(self._read(REG_START_FREQUENCY, 3), "big")
        if readback != start_code:
            raise ChipReadbackMismatch(f"{self.name}: start frequency written as 0x{start_code:06X} "
                                       f"read back as 0x{readback:06X}")
        self._start_code, self._settling_cycles = start_code, settling_cycles

    def start(self) -> None:
        """Standby, reset, excite at the start frequency, let it settle, start the sweep.

        On return the chip is measuring the first point; :meth:`measure` collects it.
        """
        self._require_configured()
        self._command(FN_STANDBY)
        self._i2c.write_byte_data(self.address, REG_CONTROL_LB, CONTROL_LB_RESET)
        self._command(FN_INITIALISE)
        self._clock.sleep(self.init_settle_s)
        self._command(FN_START_SWEEP)
        self._running = self._fresh_point = True

    def measure(self, *, repeat: bool = True) -> complex:
        """The DFT codes of one point as complex(real, imaginary).

        The point is the one :meth:`start` or :meth:`increment` began; once that
        has been collected, ``repeat=True`` has the chip measure the same
        frequency again (``repeat=False`` then raises RuntimeError instead).
        Raises :class:`ChipNotResponding` if the chip never reports valid data.
        """
        if not self._running:
            raise RuntimeError(f"{self.name}: call start() before measure()")
        if not self._fresh_point:
            if not repeat:
                raise RuntimeError(f"{self.name}: no new point is being measured; increment() or repeat")
            self._command(FN_REPEAT)
        self._fresh_point = False
        self._clock.sleep(self.measurement_time_s())     # the chip cannot be done sooner: poll once, not often
        self._wait_for(STATUS_VALID_DATA, TIMEOUT_FACTOR * self.measurement_time_s() + TIMEOUT_SLACK_S,
                       "valid data")
        raw = self._read(REG_REAL, 4)
        return complex(int.from_bytes(raw[:2], "big", signed=True), int.from_bytes(raw[2:], "big", signed=True))

    def increment(self) -> None:
        """Step to the next frequency of the sweep; :meth:`measure` collects the point."""
        if not self._running:
            raise RuntimeError(f"{self.name}: call start() before increment()")
        self._command(FN_INCREMENT)
        self._fresh_point = True

    def sweep_complete(self) -> bool:
        """Whether the last point of the configured sweep has been measured (status bit 2)."""
        return bool(self._read(REG_STATUS, 1)[0] & STATUS_SWEEP_COMPLETE)

    def set_pga(self, gain: int) -> None:
        """Change the receive PGA (x1 or x5) without restarting.

        The PGA sits between the current-to-voltage amplifier and the ADC, so a
        No-operation command carrying the new bit is enough [recall: verify]; a
        point measured across the change mixes two gains, so the next
        :meth:`measure` repeats it.
        """
        self._pga_bit = self._pga_bit_of(gain)
        self._command(FN_NOP)
        self._fresh_point = False

    def set_output_range(self, vpp: float) -> None:
        """Change the excitation amplitude without restarting.

        A No-operation command carrying the new range bits switches the output at
        once; the settling cycles of the next (repeated) point cover the step for
        a DC-coupled load. The range also moves the output's DC bias, so a front
        end that AC-couples the excitation should :meth:`start` again instead.
        """
        self._range_bits = self._range_bits_of(vpp)
        self._command(FN_NOP)
        self._fresh_point = False

    def temperature_c(self) -> float:
        """The die temperature in degrees Celsius (about 0.8 ms).

        The sweep is assumed to survive the command [recall: verify]; its next point is repeated.
        """
        self._command(FN_MEASURE_TEMPERATURE)
        self._fresh_point = False
        self._wait_for(STATUS_VALID_TEMPERATURE, TIMEOUT_FACTOR * TEMPERATURE_TIME_S + TIMEOUT_SLACK_S,
                       "temperature")
        code = int.from_bytes(self._read(REG_TEMPERATURE, 2), "big") & 0x3FFF
        if code >= 0x2000:
            code -= 0x4000
        return code / 32

    def power_down(self) -> None:
        """Stop the excitation and power the chip down (its power-on state); :meth:`start` wakes it."""
        self._command(FN_POWER_DOWN)
        self._running = self._fresh_point = False

    def measurement_time_s(self) -> float:
        """Chip-side time of one point at the start frequency: settling cycles / f + 1024 samples at MCLK/16.

        The start frequency is the lowest of an upward sweep, so this bounds
        every point; the I2C transfers come on top.
        """
        self._require_configured()
        assert self._start_code is not None     # configured
        start_hz = self._start_code * (self.mclk_hz / 4) / 2**27
        return self._settling_cycles / start_hz + DFT_SAMPLES / (self.mclk_hz / 16)

    @staticmethod
    def is_saturated(z: complex, limit: float = CODE_LIMIT) -> bool:
        """Whether codes ``z`` reach ``limit`` in magnitude or an end of the int16 range (ADC clipped)."""
        return abs(z) >= limit or any(part in (INT16_MIN, INT16_MAX) for part in (z.real, z.imag))

    def _code(self, hz: float, what: str) -> int:
        code = round(hz * 2**27 / (self.mclk_hz / 4))
        if not 0 <= code < 2**24:
            raise ValueError(f"{self.name}: {what} {hz!r} Hz gives code {code}, "
                             f"which does not fit 24 bits at MCLK {self.mclk_hz:g} Hz")
        return code

    def _settling_word(self, cycles: int) -> tuple[int, int]:
        """The settling register (D10..D9 multiplier, D8..D0 count) and the cycles it gives."""
        if not isinstance(cycles, int) or not 0 <= cycles <= self.MAX_SETTLING_CYCLES:
            raise ValueError(f"{self.name}: settling cycles {cycles!r} is outside 0..{self.MAX_SETTLING_CYCLES}")
        multiplier, bits = (1, 0b00) if cycles <= 511 else (2, 0b01) if cycles <= 1022 else (4, 0b11)
        count = -(-cycles // multiplier)
        return bits << 9 | count, count * multiplier

    def _range_bits_of(self, vpp: float) -> int:
        if vpp not in self.OUTPUT_RANGES_VPP:
            raise ValueError(f"{self.name}: output range {vpp!r} V p-p is not one of {sorted(self.OUTPUT_RANGES_VPP)}")
        return self.OUTPUT_RANGES_VPP[vpp]

    def _pga_bit_of(self, gain: int) -> int:
        if gain not in self.PGA_GAINS:
            raise ValueError(f"{self.name}: PGA gain {gain!r} is not one of {self.PGA_GAINS}")
        return 1 if gain == 1 else 0

    def _require_configured(self) -> None:
        if self._start_code is None:
            raise RuntimeError(f"{self.name}: call configure() first")

    def _command(self, function: int) -> None:
        """Write the control register's high byte: the function code with the shadowed range and PGA bits."""
        self._i2c.write_byte_data(self.address, REG_CONTROL_HB, function << 4 | self._range_bits << 1 | self._pga_bit)

    def _write_register(self, first: int, value: int, n_bytes: int) -> None:
        """Write a multi-byte register most significant byte first, one ``[reg, value]`` write per byte."""
        for offset, byte in enumerate(value.to_bytes(n_bytes, "big")):
            self._i2c.write_byte_data(self.address, first + offset, byte)

    def _read(self, register: int, n: int) -> bytes:
        """Set the pointer, then a receive byte (n = 1) or a block read joined to its read."""
        self._i2c.write_byte_data(self.address, CMD_SET_POINTER, register)
        if n == 1:
            return bytes([self._i2c.read_byte(self.address)])
        return self._i2c.write_read(self.address, bytes([CMD_BLOCK_READ, n]), n)

    def _wait_for(self, bit: int, timeout_s: float, what: str) -> None:
        """Poll the status register until ``bit`` is set, or raise ChipNotResponding after ``timeout_s``."""
        deadline = self._clock.monotonic() + timeout_s
        while True:
            status = self._read(REG_STATUS, 1)[0] & STATUS_MASK
            if status & bit:
                return
            if self._clock.monotonic() >= deadline:
                raise ChipNotResponding(f"{self.name}: no {what} within {timeout_s * 1e3:.2f} ms "
                                        f"(status 0x{status:02X}); was it reset or powered down?")
            self._clock.sleep(self.poll_interval_s)
