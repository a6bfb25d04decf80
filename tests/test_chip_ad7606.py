"""AD7606 driver against its emulator through the chip-select decoder: trace, timing, BUSY, RESET, RANGE, faults."""

import numpy as np
import pytest

from appliance.drivers.ad7606 import CONVERSION_S, AD7606Array, codes_of
from appliance.drivers.decoder import ChipSelectDecoder
from appliance.drivers.emulated.ad7606 import AD7606Pins, EmulatedAD7606
from appliance.drivers.emulated.adg1414 import EmulatedChipSelectDecoder
from appliance.drivers.emulated.buses import (BusTiming, EmulatedGPIOLines, EmulatedSPIDevice, EmulatorViolation,
                                              FaultPlan, GPIOBank)
from appliance.drivers.emulated.clock import SimulatedClock
from appliance.errors import ChipNotResponding

ADDRESS = ("GPIO4", "GPIO5")
LINES = dict(convst="GPIO17", busy="GPIO27", reset="GPIO22", range_line="GPIO23")


class Rig:
    """Three AD7606s on a two-line decoder; chip k's input n reads ``level(k, n, t)`` volts."""

    def __init__(self, level=lambda k, n, t: 0.5 * (k + 1) - 0.1 * n, *, oversampling=1, mode=2,
                 speed_hz=15_625_000, noise_lsb=0.0, chips=3, reset=True, busy_wired=True):
        self.clock, self.log = SimulatedClock(), []
        self.bank = GPIOBank(self.clock, ["GPIO4", "GPIO5", "GPIO17", "GPIO22", "GPIO23", "GPIO27"], self.log)
        self.chips = [EmulatedAD7606(self.clock, lambda t, k=k: np.array([level(k, n, t) for n in range(8)]),
                                     oversampling=oversampling, noise_lsb=noise_lsb, seed=k) for k in range(chips)]
        self.pins = AD7606Pins(self.bank, self.chips, convst="GPIO17", reset="GPIO22", range_line="GPIO23")
        if busy_wired:
            self.bank.connect("GPIO27", self.pins)
        self.decoder = EmulatedChipSelectDecoder(self.bank, ADDRESS, dict(enumerate(self.chips)))
        timing = BusTiming()
        self.spi = EmulatedSPIDevice("/dev/spidev1.0", mode, speed_hz, self.decoder, self.clock, timing, self.log,
                                     FaultPlan())
        request = AD7606Array.line_request(address_lines=ADDRESS, **LINES)
        self.lines = EmulatedGPIOLines(self.bank, request, "AD7606 converters", timing)
        self.array = AD7606Array(self.lines, self.clock, ChipSelectDecoder(self.spi, self.lines, ADDRESS),
                                 n_chips=chips, oversampling=oversampling, **LINES)
        if reset:
            self.array.reset()

    def calls(self, kind=None):
        return [t for t in self.log if kind is None or t.kind == kind]


def expected_code(volts, full_scale=10.0):
    return int(np.clip(round(volts / full_scale * 32768), -32768, 32767))


def test_codes_of_decodes_big_endian_twos_complement():
    assert codes_of(bytes([0x7F, 0xFF, 0x80, 0x00, 0xFF, 0xFF, 0, 1] + [0] * 8)) == (32767, -32768, -1, 1, 0, 0, 0, 0)
    with pytest.raises(ValueError, match="16 bytes"):
        codes_of(bytes(15))


def test_golden_trace_of_a_conversion_and_a_read():
    rig = Rig()
    rig.log.clear()
    rig.array.convert()
    codes = rig.array.read(1)
    kinds = [(t.kind, t.target) for t in rig.log]
    assert kinds == [("gpio", "GPIO17"), ("gpio", "GPIO4,GPIO5,GPIO17"), ("spi", "/dev/spidev1.0")]
    assert rig.log[1].sent == bytes([1, 0, 0])              # address 1, and CONVST back low in the same call
    assert codes == tuple(expected_code(1.0 - 0.1 * n) for n in range(8))


def test_range_pin_halves_the_full_scale_and_rides_with_the_next_call():
    rig = Rig()
    rig.array.convert()
    wide = rig.array.read(0)
    rig.array.set_range(5.0)
    rig.log.clear()
    rig.array.convert()
    narrow = rig.array.read(0)
    assert rig.log[0].target == "GPIO23" and rig.log[0].sent == bytes([0])     # RANGE low, before the edge
    assert rig.log[1].target == "GPIO17" and rig.log[1].sent == bytes([1])
    assert narrow == tuple(expected_code(0.5 - 0.1 * n, 5.0) for n in range(8))
    assert all(abs(n - 2 * w) <= 1 for n, w in zip(narrow, wide))


def test_busy_is_waited_for_the_oversampled_conversion_time():
    rig = Rig(oversampling=16)
    start = rig.clock.monotonic()
    rig.array.convert()
    assert rig.clock.monotonic() - start >= CONVERSION_S[16] and rig.pins.level(rig.clock.monotonic()) == 0
    assert rig.array.read(2)[0] == expected_code(1.5)


def test_oversampling_averages_the_converter_noise():
    spread = {}
    for ratio in (1, 16):
        rig = Rig(level=lambda k, n, t: 0.25, oversampling=ratio, noise_lsb=4.0, chips=1)
        codes = []
        for _ in range(300):
            rig.array.convert()
            codes.append(rig.array.read(0)[0])
        spread[ratio] = np.std(codes)
    assert 3.0 < spread[1] < 5.0
    assert 0.6 < spread[16] / (spread[1] / 4) < 1.6


def test_an_input_that_moves_during_an_oversampled_conversion_is_averaged():
    step_at = [np.inf]
    rig = Rig(level=lambda k, n, t: 0.0 if t < step_at[0] else 2.0, oversampling=8, chips=1)
    rig.lines.set_values({"GPIO17": 1})                           # the first sample is taken at the edge
    step_at[0] = rig.clock.monotonic() + CONVERSION_S[8] / 2 - 1e-9
    rig.clock.sleep(CONVERSION_S[8])
    assert rig.array.read(0)[0] == expected_code(1.0)              # four samples of eight after the step


def test_a_driver_that_does_not_wait_for_busy_reads_the_previous_conversion():
    value = [0.5]
    rig = Rig(level=lambda k, n, t: value[0], oversampling=64, chips=1)
    rig.array.convert()
    assert rig.array.read(0)[0] == expected_code(0.5)
    value[0] = 1.5

    class Hasty(AD7606Array):                     # the planted bug: CONVST, then read at once
        def convert(self):
            self._write(self._pending())
            self.gpio.set_values({self.convst: 1})
            self._written[self.convst] = 1

    hasty = Hasty(rig.lines, rig.clock, rig.array.decoder, n_chips=1, oversampling=64, **LINES)
    hasty._written = dict(rig.array._written)
    hasty.convert()
    assert hasty.read(0)[0] == expected_code(0.5)                    # stale: BUSY was still high
    assert any("before BUSY fell" in w for w in rig.chips[0].warnings)
    rig.array.convert()
    assert rig.array.read(0)[0] == expected_code(1.5)


def test_a_conversion_before_the_reset_pulse_is_refused():
    rig = Rig(reset=False)
    with pytest.raises(EmulatorViolation, match="RESET"):
        rig.array.convert()


def test_range_changed_with_the_convst_edge_or_during_a_conversion_is_refused():
    rig = Rig(oversampling=64)
    with pytest.raises(EmulatorViolation, match="same call as the CONVST"):
        rig.lines.set_values({"GPIO23": 0, "GPIO17": 1})
    rig = Rig(oversampling=64)
    rig.lines.set_values({"GPIO17": 1})
    with pytest.raises(EmulatorViolation, match="during a conversion"):
        rig.lines.set_values({"GPIO23": 0})


@pytest.mark.parametrize("mode", [0, 1])
def test_spi_modes_with_sclk_idling_low_are_refused(mode):
    rig = Rig(mode=mode)
    rig.array.convert()
    with pytest.raises(EmulatorViolation, match="SPI mode"):
        rig.array.read(0)


def test_too_fast_a_clock_and_odd_frames_are_refused():
    rig = Rig(speed_hz=25_000_000)
    rig.array.convert()
    with pytest.raises(EmulatorViolation, match="exceeds"):
        rig.array.read(0)
    rig = Rig()
    rig.array.convert()
    rig.array.decoder.select(0)
    with pytest.raises(EmulatorViolation, match="16-bit words"):
        rig.spi.transfer(bytes(3))


def test_frames_continue_where_the_last_stopped_and_an_empty_output_reads_the_pull_up():
    rig = Rig()
    rig.array.convert()
    rig.array.decoder.select(0)
    first, rest = rig.spi.transfer(bytes(4)), rig.spi.transfer(bytes(12))
    assert codes_of(first + rest) == tuple(expected_code(0.5 - 0.1 * n) for n in range(8))
    rig.array.decoder.select(3)                                  # nothing on output 3 of this board
    assert rig.spi.transfer(bytes(16)) == b"\xff" * 16


def test_busy_that_never_falls_is_reported():
    rig = Rig(busy_wired=False)
    with pytest.raises(ChipNotResponding, match="BUSY on GPIO27 did not fall"):
        rig.array.convert()


def test_busys_edge_stays_queued_until_a_wait_takes_it_or_a_drain_discards_it():
    rig = Rig()
    for _ in range(2):
        rig.lines.set_values({"GPIO17": 1})
        rig.lines.set_values({"GPIO17": 0})
        rig.clock.sleep(2 * CONVERSION_S[1])
    assert rig.lines.wait_edge("GPIO27", 0.0) is True                 # came long before the wait
    assert rig.lines.drain_edges("GPIO27") == 1
    assert rig.lines.wait_edge("GPIO27", 1.0) is False


def test_read_many_starts_with_the_converter_already_addressed():
    rig = Rig()
    rig.array.convert()
    rig.array.read(2)
    rig.array.convert()
    rig.log.clear()
    codes = rig.array.read_many([0, 2, 1])
    assert list(codes) == [2, 0, 1] and rig.decoder.selections[-3:] == [2, 0, 1]
    gpio = [t for t in rig.log if t.kind == "gpio"]
    assert len(gpio) == 2 and "GPIO17" in gpio[0].target         # CONVST low rides with the first address


def test_forget_sends_the_levels_again():
    rig = Rig()
    rig.array.convert()
    rig.array.read(1)
    rig.array.forget()
    rig.log.clear()
    rig.array.convert()
    assert rig.log[0].target == "GPIO17,GPIO23"
