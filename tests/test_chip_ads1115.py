"""ADS1115 driver against its register-level emulator: golden trace, timing, ALERT/RDY, faults."""

import bisect

import numpy as np
import pytest

from appliance.drivers.ads1115 import ADS1115, READY_MARGIN_S, config_word, longest_conversion_s
from appliance.drivers.bus import FALLING, PULL_UP, LineRequest
from appliance.drivers.emulated.ads1115 import EmulatedADS1115
from appliance.drivers.backend import emulated_board, open_front_end
from appliance.drivers.emulated.buses import BusTiming, EmulatedGPIOLines, EmulatedI2CBus, EmulatorViolation, GPIOBank
from appliance.drivers.emulated.clock import SimulatedClock
from appliance.drivers.profile import board_profile
from appliance.errors import ChipNotResponding, ChipReadbackMismatch, TransferFailed
from conftest import sensor_of

READY_REQUEST = LineRequest(outputs={}, inputs={"GPIO4": FALLING}, bias={"GPIO4": PULL_UP})
LSB_4V = 4.096 / 32768


def rig(volts=lambda pin, t: 1.0 if pin == "AIN0" else 0.0, ready=True, wired=True, **chip_options):
    """The chip on I2C, its ALERT/RDY on GPIO4 (``wired``: the wire is intact) when the driver uses ``ready``."""
    clock = SimulatedClock()
    log = []
    bus = EmulatedI2CBus(1, clock, BusTiming(), log)
    chip = EmulatedADS1115(clock, volts, **chip_options)
    bus.attach(chip)
    lines = None
    if ready:
        bank = GPIOBank(clock, ["GPIO4"], log)
        if wired:
            bank.connect("GPIO4", chip)
        lines = EmulatedGPIOLines(bank, READY_REQUEST, "adc", BusTiming())
    return clock, bus, chip, ADS1115(bus, clock, ready=lines, ready_line="GPIO4" if ready else None), log


class SteppedInput:
    """AIN0 as steps in time (the emulator may sample a past instant: a conversion's end is taken lazily)."""

    def __init__(self):
        self.times, self.levels = [0.0], [0.0]

    def step(self, t, volts):
        self.times.append(t)
        self.levels.append(volts)

    def __call__(self, pin, t):
        return self.levels[bisect.bisect_right(self.times, t) - 1] if pin == "AIN0" else 0.0


def readings_of_changing_inputs(adc, clock, ain0, n, *, self_test_every=100, gaps_s=(0.0, 0.3e-3, 5e-3), seed=1):
    """``n`` readings of AIN0, each of a new input, after a gap drawn from ``gaps_s``, with the self-test's chip
    check before the first and every ``self_test_every``: (codes read, codes of each reading's own input)."""
    rng = np.random.default_rng(seed)
    inputs, gaps = rng.uniform(0.0, 4.0, n), rng.choice(gaps_s, n)
    codes = []
    for i in range(n):
        if i % self_test_every == 0:
            adc.check()
        clock.sleep(gaps[i])
        ain0.step(clock.monotonic(), inputs[i])
        codes.append(adc.read_volts("AIN0", 4.096, 860)[1])
    return codes, [round(v / LSB_4V) for v in inputs]


def test_config_word_packs_the_fields():
    # AIN0 single-ended (100), +/-4.096 V (001), single shot, 860 SPS (111), comparator on after 1 (00)
    assert config_word("AIN0", 4.096, 860, ready_pin=True) == 0b0_100_001_1_111_0_0_0_00
    assert config_word("AIN0-AIN1", 2.048, 128, ready_pin=False) == 0x0583
    with pytest.raises(ValueError, match="full scale 3.0"):
        config_word("AIN0", 3.0, 860, ready_pin=True)


def test_golden_trace_of_one_conversion():
    clock, bus, chip, adc, log = rig()
    log.clear()
    volts, code = adc.read_volts("AIN0", 4.096, 860)
    writes = [(t.kind, t.sent) for t in log if t.kind.startswith("i2c")]
    assert writes[0] == ("i2c-write", bytes([0x01, 0xC3, 0xE0]))      # OS | config
    assert writes[-1] == ("i2c-write-read", bytes([0x00]))            # pointer to conversion, read 2
    assert code == round(1.0 / (4.096 / 32768)) == 8000 and volts == pytest.approx(1.0)


def test_the_ready_pin_is_configured_and_waited_on():
    clock, bus, chip, adc, log = rig()
    assert chip.registers[0x03] & 0x8000 and not chip.registers[0x02] & 0x8000
    start = clock.monotonic()
    adc.read_volts("AIN0", 4.096, 860)
    assert clock.monotonic() - start >= chip.period_s(0xC3E0)           # waited the whole conversion
    assert chip.conversions == 1


def test_without_the_pin_the_driver_polls_os():
    clock, bus, chip, adc, log = rig(ready=False)
    volts, code = adc.read_volts("AIN0", 4.096, 860)
    assert code == 8000
    assert any(t.kind == "i2c-write-read" and t.sent == bytes([0x01]) for t in log)


def test_reading_before_the_conversion_ends_gives_the_previous_result():
    clock, bus, chip, adc, log = rig(volts=lambda pin, t: 0.5 if t < 0.1 else 1.5)
    adc.read_volts("AIN0", 4.096, 860)
    clock.sleep(0.1)
    adc.start("AIN0", 4.096, 860)
    assert adc.read_register(0x00) == 4000                            # still the 0.5 V result
    assert adc.read_code(860) == 12000


def test_a_conversion_averages_its_start_and_end():
    clock, bus, chip, adc, log = rig(volts=lambda pin, t: 0.0 if t < 0.05 else 1.0)
    clock.sleep(0.05 - 0.3e-3 - clock.monotonic())                      # start just before the step
    assert adc.read_volts("AIN0", 4.096, 860)[1] == 4000               # half of 1 V: the input moved


def test_power_on_config_and_readback_check():
    clock, bus, chip, adc, log = rig(ready=False)
    chip.reset()
    assert adc.read_register(0x01) == 0x8583
    adc.check()
    chip.registers[0x01] = 0x8000        # a chip that lost its config
    original = chip.write
    chip.write = lambda data: original(data[:1])          # ignores register data
    with pytest.raises(ChipReadbackMismatch, match="wrote 0x"):
        adc.check()


def test_a_thousand_readings_are_each_their_own_conversion_also_right_after_the_self_test():
    ain0 = SteppedInput()
    clock, bus, chip, adc, log = rig(volts=ain0)
    codes, expected = readings_of_changing_inputs(adc, clock, ain0, 1000)
    assert codes == expected
    assert chip.conversions == 1000


def test_the_self_test_leaves_a_ready_edge_pending_and_a_driver_that_does_not_drain_reads_one_behind(monkeypatch):
    ain0 = SteppedInput()
    clock, bus, chip, adc, log = rig(volts=ain0)
    adc.check()
    assert adc.ready.get_values(["GPIO4"]) == {"GPIO4": 0}            # conversion-ready mode, idle: asserted
    monkeypatch.setattr(adc.ready, "drain_edges", lambda name: 0)     # the planted bug: the driver
    codes, expected = readings_of_changing_inputs(adc, clock, ain0, 50, self_test_every=1000, gaps_s=(5e-3,))
    assert codes[0] == 0 and codes[1:] == expected[:-1]               # each is the conversion before
    monkeypatch.undo()
    clock.sleep(longest_conversion_s(860))                            # the last one it started ends unread
    codes, expected = readings_of_changing_inputs(adc, clock, ain0, 50, self_test_every=1000, seed=2)
    assert codes == expected


def test_the_pin_is_high_while_converting_and_falls_at_the_end():
    clock, bus, chip, adc, log = rig()
    adc.check()
    adc.start("AIN0", 4.096, 8)
    assert adc.ready.get_values() == {"GPIO4": 1}
    clock.sleep(longest_conversion_s(8))
    assert adc.ready.get_values() == {"GPIO4": 0}
    assert adc.ready.drain_edges("GPIO4") == 1                        # this conversion's: start drained the check's


def test_a_chip_at_the_slow_end_of_its_data_rate_is_waited_for():
    clock, bus, chip, adc, log = rig(oscillator_slow=1 / 0.9)
    assert adc.read_volts("AIN0", 4.096, 8)[1] == 8000


def test_a_dead_oscillator_is_a_named_fault_within_the_slowest_conversion_and_a_margin():
    clock, bus, chip, adc, log = rig()
    chip.period_s = lambda config: 1.0
    start = clock.monotonic()
    with pytest.raises(ChipNotResponding, match=r"ADS1115\(0x48\): ALERT/RDY on GPIO4 did not signal the end of a "
                                                r"conversion within 6\.3 ms \(one at 860 SPS takes at most 1\.32 ms\)"):
        adc.read_volts("AIN0", 4.096, 860)
    assert clock.monotonic() - start >= longest_conversion_s(860) + READY_MARGIN_S


def test_a_ready_wire_that_never_fires_is_a_named_fault_naming_the_pull_up():
    clock, bus, chip, adc, log = rig(wired=False)
    with pytest.raises(ChipNotResponding, match=r"ADS1115\(0x48\): ALERT/RDY on GPIO4 .*wire and its pull-up"):
        adc.read_volts("AIN0", 4.096, 128)


def test_the_open_drain_ready_line_must_be_pulled_up():
    clock = SimulatedClock()
    chip = EmulatedADS1115(clock, lambda pin, t: 0.0)
    bank = GPIOBank(clock, ["GPIO4"], [])
    bank.connect("GPIO4", chip)
    floating = EmulatedGPIOLines(bank, LineRequest(outputs={}, inputs={"GPIO4": FALLING}), "adc", BusTiming())
    for use in (lambda: floating.wait_edge("GPIO4", 1.0), lambda: floating.drain_edges("GPIO4"),
                floating.get_values):
        with pytest.raises(EmulatorViolation, match="GPIO4 of adc: ADS1115 drives it open drain.*pull-up"):
            use()


def test_the_front_end_requests_the_ready_line_with_the_pull_up():
    board = emulated_board(board_profile({}), sensor_of("grid-4x4"))
    front_end = open_front_end(board, board.profile)
    ready = board.profile.gpio["adc_ready"]
    assert front_end.inputs.request.bias == {ready: PULL_UP}
    assert front_end.adc.ready_line == ready
    board.close()


def test_input_beyond_full_scale_clips_and_a_stuck_chip_repeats():
    clock, bus, chip, adc, log = rig(volts=lambda pin, t: 9.0)
    assert adc.read_volts("AIN0", 4.096, 860)[1] == 32767
    chip.stuck_code = 77
    assert adc.read_volts("AIN0", 0.256, 860)[1] == 77


def test_wrong_address_and_bad_pointer_are_not_acknowledged():
    clock, bus, chip, adc, log = rig()
    with pytest.raises(TransferFailed) as info:
        bus.read_byte(0x49)
    assert info.value.errno == 121
    with pytest.raises(TransferFailed, match="0x48"):
        bus.write(0x48, bytes([0x07]))
