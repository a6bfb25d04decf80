"""ADS1115 16-bit delta-sigma ADC on I2C: single-shot conversions, waited for on ALERT/RDY.

The front end reads the RMS-to-DC converter's output on AIN0. Each conversion is
started by writing the config register with OS = 1; without the ALERT/RDY pin the
driver sleeps the conversion time and polls OS. Registers are big-endian 16-bit
words behind a pointer byte: write [pointer, MSB, LSB]; read by writing [pointer]
then reading two bytes. Both are SMBus word transfers with the bytes swapped, so
an adapter that speaks only SMBus carries them too.

What the driver relies on, from TI's data sheet (SBAS444D, January 2018):

- 9.3.8 and 9.6.4: Hi_thresh MSB 1 with Lo_thresh MSB 0 makes ALERT/RDY a
  conversion-ready pin, as long as COMP_QUE is not 11 (11 disables it and leaves
  it high, 9.3.7). In single-shot mode the pin then outputs the OS bit: with
  COMP_POL 0 it is low whenever no conversion runs, and falls at the end of each.
  So the config write of the self-test, made while the chip is idle, pulls the
  pin low at once: that falling edge waits in the kernel's queue, and a driver
  that took it as its next conversion's end would read every result one
  conversion late. Queued edges are therefore drained before each start.
- 9.3.8: the pin is open drain and needs a pull-up (the board has no resistor:
  the line is requested with the SoC's pull-up).
- 9.4.2.1: writing OS = 1 powers the chip up in about 25 us, then it converts;
  OS reads 0 until the result is ready. 7.5: each data rate is within +/-10 %.
  A conversion that has not signalled ready by the slowest conversion time (plus
  a margin for the kernel's event delivery) is a chip fault, never a reading.
"""

from __future__ import annotations

from appliance.drivers.bus import Clock, GPIOLines, I2CBus
from appliance.errors import ChipNotResponding, ChipReadbackMismatch

CONVERSION, CONFIG, LO_THRESH, HI_THRESH = 0x00, 0x01, 0x02, 0x03

FULL_SCALES_V = (6.144, 4.096, 2.048, 1.024, 0.512, 0.256)
DATA_RATES_SPS = (8, 16, 32, 64, 128, 250, 475, 860)
INPUTS = ("AIN0-AIN1", "AIN0-AIN3", "AIN1-AIN3", "AIN2-AIN3", "AIN0", "AIN1", "AIN2", "AIN3")

OS_START = 0x8000
MODE_SINGLE = 0x0100
COMP_ASSERT_AFTER_ONE = 0x0000   # COMP_QUE = 00: ALERT/RDY active; 11 would disable it
COMP_DISABLED = 0x0003
DATA_RATE_VARIATION = 0.10       # 7.5: the internal oscillator may run 10 % slow
POWER_UP_S = 25e-6               # 9.4.2.1: a single shot wakes the chip first
READY_MARGIN_S = 5e-3            # a busy Pi may deliver the edge event milliseconds late


def longest_conversion_s(data_rate_sps: int) -> float:
    """A single-shot conversion's time from the OS write at the slowest the data sheet allows."""
    return POWER_UP_S + 1 / (data_rate_sps * (1 - DATA_RATE_VARIATION))


def config_word(input_name: str, full_scale_v: float, data_rate_sps: int, *, ready_pin: bool) -> int:
    """The config register for one single-shot conversion (OS bit clear)."""
    try:
        mux = INPUTS.index(input_name)
        pga = FULL_SCALES_V.index(full_scale_v)
        rate = DATA_RATES_SPS.index(data_rate_sps)
    except ValueError:
        raise ValueError(f"ADS1115: input {input_name!r}, full scale {full_scale_v!r} V or rate "
                         f"{data_rate_sps!r} SPS is not one the chip offers ({INPUTS}, {FULL_SCALES_V}, "
                         f"{DATA_RATES_SPS})") from None
    comparator = COMP_ASSERT_AFTER_ONE if ready_pin else COMP_DISABLED
    return (mux << 12) | (pga << 9) | MODE_SINGLE | (rate << 5) | comparator


class ADS1115:
    """One ADS1115 at ``address`` on ``i2c``; ``ready``/``ready_line`` wire its ALERT/RDY pin (optional)."""

    def __init__(self, i2c: I2CBus, clock: Clock, *, address: int = 0x48, ready: GPIOLines | None = None,
                 ready_line: str | None = None):
        if (ready is None) != (ready_line is None):
            raise ValueError("ADS1115: ready and ready_line wire the ALERT/RDY pin together: give both or neither")
        self.i2c, self.clock, self.address = i2c, clock, address
        self.ready, self.ready_line = ready, ready_line
        if ready is not None:
            self.write_register(HI_THRESH, 0x8000)
            self.write_register(LO_THRESH, 0x0000)

    def __repr__(self) -> str:
        return f"ADS1115(0x{self.address:02X})"

    def write_register(self, pointer: int, value: int) -> None:
        self.i2c.write_word_swapped(self.address, pointer, value)

    def read_register(self, pointer: int) -> int:
        return self.i2c.read_word_swapped(self.address, pointer)

    def check(self) -> None:
        """Write a config word and read it back (OS masked): the chip is there and its registers hold."""
        word = config_word("AIN0", 4.096, 860, ready_pin=self.ready is not None)
        self.write_register(CONFIG, word)
        back = self.read_register(CONFIG) & 0x7FFF
        if back != word:
            raise ChipReadbackMismatch(f"{self!r}: config register wrote 0x{word:04X}, read back 0x{back:04X}")

    def start(self, input_name: str, full_scale_v: float, data_rate_sps: int) -> float:
        """Start one conversion; returns when it should be done (monotonic seconds).

        ALERT/RDY's queued edges are drained first: any of them is older than this conversion.
        """
        word = config_word(input_name, full_scale_v, data_rate_sps, ready_pin=self.ready is not None)
        if self.ready is not None and self.ready_line is not None:
            self.ready.drain_edges(self.ready_line)
        self.write_register(CONFIG, OS_START | word)
        return self.clock.monotonic() + longest_conversion_s(data_rate_sps)

    def read_code(self, data_rate_sps: int) -> int:
        """Wait for the conversion started last, then its signed 16-bit code."""
        conversion_s = longest_conversion_s(data_rate_sps)
        if self.ready is not None and self.ready_line is not None:
            timeout_s = conversion_s + READY_MARGIN_S
            if not self.ready.wait_edge(self.ready_line, timeout_s):
                raise ChipNotResponding(f"{self!r}: ALERT/RDY on {self.ready_line} did not signal the end of a "
                                        f"conversion within {timeout_s * 1e3:.1f} ms (one at {data_rate_sps} SPS "
                                        f"takes at most {conversion_s * 1e3:.2f} ms); check the chip, the "
                                        f"ALERT/RDY wire and its pull-up")
        else:
            self.clock.sleep(conversion_s)
            for _ in range(3):
                if self.read_register(CONFIG) & OS_START:
                    break
                self.clock.sleep(conversion_s / 4)
            else:
                raise ChipNotResponding(f"{self!r}: conversion still running {conversion_s * 2e3:.1f} ms after start")
        code = self.read_register(CONVERSION)
        return code - 0x10000 if code & 0x8000 else code

    def read_volts(self, input_name: str, full_scale_v: float, data_rate_sps: int) -> tuple[float, int]:
        """One single-shot conversion: (volts, code)."""
        self.start(input_name, full_scale_v, data_rate_sps)
        code = self.read_code(data_rate_sps)
        return code * full_scale_v / 32768, code
