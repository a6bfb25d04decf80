"""AD9833 driver against its register-level emulator: exact SPI words, frequencies and the B28 pitfall."""

import pytest

from appliance.drivers.ad9833 import AD9833
from appliance.drivers.emulated.ad9833 import EmulatedAD9833
from appliance.drivers.emulated.buses import BusTiming, EmulatedSPIDevice, EmulatorViolation, FaultPlan
from appliance.drivers.emulated.clock import SimulatedClock

MCLK_HZ = 25e6
STEP_HZ = MCLK_HZ / 2**28


def wire(mode=AD9833.SPI_MODE, speed_hz=AD9833.MAX_SPEED_HZ):
    """A fresh emulator behind an SPI device; returns (driver, emulator, device, log)."""
    chip = EmulatedAD9833(mclk_hz=MCLK_HZ)
    log = []
    device = EmulatedSPIDevice("/dev/spidev0.0", mode, speed_hz, chip, SimulatedClock(), BusTiming(), log, FaultPlan())
    return AD9833(device, mclk_hz=MCLK_HZ), chip, device, log


def frames(log):
    return [list(t.sent) for t in log]


def test_start_sends_the_documented_words_golden_trace():
    driver, _, _, log = wire()
    driver.start(17_500)
    # FREQREG = round(17500 * 2**28 / 25e6) = round(187904.82) = 187905 = 0x2DE01
    # 14 LSBs: 187905 - 11 * 16384 = 7681 = 0x1E01 -> word 0x4000 | 0x1E01 = 0x5E01
    # 14 MSBs: 187905 >> 14 = 11 = 0x000B          -> word 0x4000 | 0x000B = 0x400B
    word = 0x2DE01
    assert round(17_500 * 2**28 / 25e6) == word == 187905
    assert (word & 0x3FFF, word >> 14) == (0x1E01, 0x000B)
    assert frames(log) == [[0x21, 0x00], [0x5E, 0x01], [0x40, 0x0B], [0xC0, 0x00], [0x20, 0x00]]


@pytest.mark.parametrize("frequency_hz", [5_700.0, 17_500.0, 36_400.0, 12_345.678, 1.0])
def test_emulated_output_matches_the_request_to_one_tuning_step(frequency_hz):
    driver, chip, _, _ = wire()
    driver.start(frequency_hz)
    assert abs(chip.output_hz - frequency_hz) <= STEP_HZ / 2
    assert chip.output_hz == driver.frequency_hz
    assert chip.waveform == "sine"
    assert chip.warnings == []


def test_power_on_output_is_off_until_reset_is_cleared():
    driver, chip, _, _ = wire()
    assert (chip.output_hz, chip.waveform) == (0.0, "off")
    assert driver.frequency_hz is None


def test_set_frequency_while_running_switches_only_after_the_second_half():
    driver, chip, _, log = wire()
    driver.start(10_000)
    seen = []
    chip.listeners.append(lambda: seen.append(chip.output_hz))
    driver.set_frequency(30_000)
    # round(30000 * 2**28 / 25e6) = round(322122.55) = 322123 = 19 * 16384 + 10827: words 0x6A4B, 0x4013
    word = 322123
    assert round(30_000 * 2**28 / MCLK_HZ) == word and (word & 0x3FFF, word >> 14) == (0x2A4B, 0x13)
    assert frames(log)[-2:] == [[0x6A, 0x4B], [0x40, 0x13]]
    assert seen == [word * STEP_HZ]  # one change, after the MSB word; never a half-written frequency
    assert chip.output_hz == driver.frequency_hz == pytest.approx(30_000, abs=STEP_HZ)
    assert chip.control == 0x2000  # B28 still set, running sine


def test_clearing_b28_then_a_two_word_write_gives_the_wrong_frequency_and_a_warning():
    target_hz = 10_000
    word = round(target_hz * 2**28 / MCLK_HZ)  # 107374: LSBs 9070, MSBs 6
    lsb, msb = 0x4000 | (word & 0x3FFF), 0x4000 | (word >> 14)
    driver, chip, device, _ = wire()
    driver.start(17_500)
    for w in (0x0000, lsb, msb):  # the public-code bug: 0x0000 "for sine", then B28-style halves
        device.transfer(w.to_bytes(2, "big"))
    # B28 = 0, HLB = 0: both writes land in the 14 LSBs; the MSBs (11) of 17.5 kHz remain
    assert chip.freq[0] == (11 << 14) | 6
    assert chip.output_hz == ((11 << 14) | 6) * STEP_HZ
    assert abs(chip.output_hz - target_hz) > 6_000
    assert len(chip.warnings) == 1 and "B28" in chip.warnings[0] and "FREQ0" in chip.warnings[0]

    good_driver, good_chip, _, _ = wire()
    good_driver.start(17_500)
    good_driver.set_frequency(target_hz)
    assert good_chip.freq[0] == word
    assert good_chip.output_hz == word * STEP_HZ
    assert good_chip.warnings == []


def test_single_half_write_with_b28_clear_is_not_flagged():
    _, chip, device, _ = wire()
    for w in (0x1000, 0x4005, 0x0000, 0x4007):  # HLB=1: MSBs = 5; HLB=0: LSBs = 7
        device.transfer(w.to_bytes(2, "big"))
    assert chip.freq[0] == (5 << 14) | 7
    assert chip.warnings == []


@pytest.mark.parametrize(("waveform", "control"), [("triangle", 0x2002), ("square", 0x2028)])
def test_waveforms(waveform, control):
    driver, chip, _, log = wire()
    driver.start(1_000, waveform)
    assert list(log[-1].sent) == [control >> 8, control & 0xFF]
    assert chip.waveform == waveform == driver.waveform
    assert chip.output_hz == driver.frequency_hz


def test_stop_turns_the_output_off_with_b28_kept():
    driver, chip, _, log = wire()
    driver.start(20_000)
    calls = []
    chip.listeners.append(lambda: calls.append(chip.waveform))
    driver.stop()
    assert list(log[-1].sent) == [0x21, 0xC0]
    assert (chip.output_hz, chip.waveform, driver.frequency_hz) == (0.0, "off", None)
    assert calls == ["off"]
    with pytest.raises(RuntimeError, match="stopped"):
        driver.set_frequency(1_000)


def test_wrong_spi_mode_is_rejected():
    driver, _, _, _ = wire(mode=0)
    with pytest.raises(EmulatorViolation, match="mode 0"):
        driver.start(1_000)


def test_too_fast_clock_is_rejected():
    driver, _, _, _ = wire(speed_hz=50_000_000)
    with pytest.raises(EmulatorViolation, match="exceeds"):
        driver.start(1_000)


@pytest.mark.parametrize("data", [b"\x21", b"\x21\x00\x40"])
def test_frame_of_odd_length_is_rejected(data):
    _, _, device, _ = wire()
    with pytest.raises(EmulatorViolation, match="16-bit words"):
        device.transfer(data)


def test_several_words_in_one_frame_are_taken_in_order():
    _, chip, device, _ = wire()
    device.transfer(bytes([0x21, 0x00, 0x5E, 0x01, 0x40, 0x0B, 0x20, 0x00]))
    assert chip.freq[0] == 187905 and chip.waveform == "sine"


@pytest.mark.parametrize("control", [0x2001, 0x2004, 0x2010, 0x2200, 0x2022])
def test_reserved_control_bits_are_rejected(control):
    _, _, device, _ = wire()
    with pytest.raises(EmulatorViolation, match="reserved"):
        device.transfer(control.to_bytes(2, "big"))


@pytest.mark.parametrize("frequency_hz", [0, -5.0, 12_500_000.5, float("nan")])
def test_frequency_out_of_range_raises(frequency_hz):
    driver, _, _, log = wire()
    with pytest.raises(ValueError, match=repr(frequency_hz)):
        driver.start(frequency_hz)
    assert log == []


def test_nyquist_limit_itself_is_accepted():
    driver, chip, _, _ = wire()
    driver.start(MCLK_HZ / 2)
    assert driver.frequency_word(MCLK_HZ / 2) == 2**27
    assert chip.output_hz == 12_500_000.0


def test_reset_restores_power_on_state():
    driver, chip, _, _ = wire()
    driver.start(5_000)
    chip.reset()
    assert (chip.control, chip.freq, chip.phase, chip.output_hz) == (0x0100, [0, 0], [0, 0], 0.0)
