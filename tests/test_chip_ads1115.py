"""ADS1115 driver against its register-level emulator: golden trace, timing, ALERT/RDY, faults."""

import pytest

from appliance.drivers.ads1115 import ADS1115, config_word
from appliance.drivers.bus import FALLING, LineRequest
from appliance.drivers.emulated.ads1115 import EmulatedADS1115
from appliance.drivers.emulated.buses import BusTiming, EmulatedGPIOLines, EmulatedI2CBus, GPIOBank
from appliance.drivers.emulated.clock import SimulatedClock
from appliance.errors import ChipNotResponding, ChipReadbackMismatch, TransferFailed


def rig(volts=lambda pin, t: 1.0 if pin == "AIN0" else 0.0, ready=True):
    clock = SimulatedClock()
    log = []
    bus = EmulatedI2CBus(1, clock, BusTiming(), log)
    chip = EmulatedADS1115(clock, volts)
    bus.attach(chip)
    lines = None
    if ready:
        bank = GPIOBank(clock, ["GPIO4"], log)
        bank.connect("GPIO4", chip)
        lines = EmulatedGPIOLines(bank, LineRequest(outputs={}, inputs={"GPIO4": FALLING}), "adc", BusTiming())
    return clock, bus, chip, ADS1115(bus, clock, ready=lines, ready_line="GPIO4" if ready else None), log


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


def test_ready_never_coming_is_a_named_fault():
    clock, bus, chip, adc, log = rig()
    chip.period_s = lambda config: 1.0                    # a dead oscillator
    with pytest.raises(ChipNotResponding, match="ALERT/RDY on GPIO4"):
        adc.read_volts("AIN0", 4.096, 860)


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
