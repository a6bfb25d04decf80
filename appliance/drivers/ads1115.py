"""ADS1115 16-bit delta-sigma ADC on I2C: single-shot conversions, waited for on ALERT/RDY.

The front end reads the RMS-to-DC converter's output on AIN0. Each conversion is
started by writing the config register with OS = 1 and finishes one sample period
later; the ALERT/RDY pin, set up as a conversion-ready output (Hi_thresh MSB 1,
Lo_thresh MSB 0, comparator enabled), falls when it does, so the driver waits on
a GPIO edge instead of polling the bus. Without the pin it sleeps the period and
polls OS.

Registers are big-endian 16-bit words behind a pointer byte: write [pointer, MSB,
LSB]; read by writing [pointer] then reading two bytes.
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
RATE_TOLERANCE = 1.1             # the internal oscillator may run 10 % slow


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
        self.i2c, self.clock, self.address = i2c, clock, address
        self.ready, self.ready_line = ready, ready_line
        if ready is not None:
            self.write_register(HI_THRESH, 0x8000)
            self.write_register(LO_THRESH, 0x0000)

    def __repr__(self) -> str:
        return f"ADS1115(0x{self.address:02X})"

    def write_register(self, pointer: int, value: int) -> None:
        self.i2c.write(self.address, bytes([pointer, value >> 8, value & 0xFF]))

    def read_register(self, pointer: int) -> int:
        high, low = self.i2c.write_read(self.address, bytes([pointer]), 2)
        return high << 8 | low

    def check(self) -> None:
        """Write a config word and read it back (OS masked): the chip is there and its registers hold."""
        word = config_word("AIN0", 4.096, 860, ready_pin=self.ready is not None)
        self.write_register(CONFIG, word)
        back = self.read_register(CONFIG) & 0x7FFF
        if back != word:
            raise ChipReadbackMismatch(f"{self!r}: config register wrote 0x{word:04X}, read back 0x{back:04X}")

    def start(self, input_name: str, full_scale_v: float, data_rate_sps: int) -> float:
        """Start one conversion; returns when it should be done (monotonic seconds)."""
        word = config_word(input_name, full_scale_v, data_rate_sps, ready_pin=self.ready is not None)
        self.write_register(CONFIG, OS_START | word)
        return self.clock.monotonic() + RATE_TOLERANCE / data_rate_sps

    def read_code(self, data_rate_sps: int) -> int:
        """Wait for the conversion started last, then its signed 16-bit code."""
        period_s = RATE_TOLERANCE / data_rate_sps
        if self.ready is not None:
            if not self.ready.wait_edge(self.ready_line, 2 * period_s):
                raise ChipNotResponding(f"{self!r}: ALERT/RDY on {self.ready_line} did not signal the end of a "
                                        f"conversion within {2 * period_s * 1e3:.1f} ms")
        else:
            self.clock.sleep(period_s)
            for _ in range(3):
                if self.read_register(CONFIG) & OS_START:
                    break
                self.clock.sleep(period_s / 4)
            else:
                raise ChipNotResponding(f"{self!r}: conversion still running {period_s * 2e3:.1f} ms after start")
        code = self.read_register(CONVERSION)
        return code - 0x10000 if code & 0x8000 else code

    def read_volts(self, input_name: str, full_scale_v: float, data_rate_sps: int) -> tuple[float, int]:
        """One single-shot conversion: (volts, code)."""
        self.start(input_name, full_scale_v, data_rate_sps)
        code = self.read_code(data_rate_sps)
        return code * full_scale_v / 32768, code
