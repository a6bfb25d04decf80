"""ADG725 and ADG731 drivers against their emulators: exact control words and the switch state."""

import pytest

from appliance.drivers.adg7xx import ADG725, ADG731
from appliance.drivers.emulated.adg7xx import EmulatedADG725, EmulatedADG731
from appliance.drivers.emulated.buses import BusTiming, EmulatedSPIDevice, EmulatorViolation, FaultPlan
from appliance.drivers.emulated.clock import SimulatedClock


def wire(chip, mode=1, speed_hz=10_000_000):
    log = []
    device = EmulatedSPIDevice("/dev/spidev0.1", mode, speed_hz, chip, SimulatedClock(), BusTiming(), log, FaultPlan())
    return device, log


def adg725(mode=ADG725.SPI_MODE):
    chip = EmulatedADG725()
    device, log = wire(chip, mode)
    return ADG725(device), chip, device, log


def frames(log):
    return [list(t.sent) for t in log]


@pytest.mark.parametrize(("a", "b", "expected_frames", "expected_selection"), [
    (3, None, [[0x23]], (3, None)),
    (None, 7, [[0x47]], (None, 7)),
    (5, 5, [[0x05]], (5, 5)),
    (2, 9, [[0x22], [0x49]], (2, 9)),
    (15, 0, [[0x2F], [0x40]], (15, 0)),
    (None, None, [], (None, None)),
])
def test_adg725_select_golden_words(a, b, expected_frames, expected_selection):
    driver, chip, _, log = adg725()
    driver.select(a, b)
    assert frames(log) == expected_frames
    assert driver.selection == expected_selection
    assert (chip.selected("A"), chip.selected("B")) == expected_selection


def test_adg725_off_golden_word_and_state():
    driver, chip, _, log = adg725()
    driver.select(2, 9)
    driver.off()
    assert frames(log)[-1] == [0x80]
    assert driver.selection == (None, None)
    assert (chip.selected("A"), chip.selected("B")) == (None, None)


def test_adg725_sends_only_the_mux_that_changes():
    driver, chip, _, log = adg725()
    driver.select(2, 9)
    driver.select(2, 4)
    assert frames(log) == [[0x22], [0x49], [0x44]]
    driver.select(6, 6)
    assert frames(log)[-1] == [0x06]
    driver.select(6, 6)
    assert len(log) == 4
    assert (chip.selected("A"), chip.selected("B")) == (6, 6)


def test_adg725_mux_switched_off_stays_off_when_the_other_is_set():
    driver, chip, device, _ = adg725()
    driver.select(2, 9)
    driver.off()
    driver.select(3, None)
    assert (chip.selected("A"), chip.selected("B")) == (3, None)
    device.transfer(bytes([0x60]))  # EN = 0, both chip selects high: nothing changes
    assert (chip.selected("A"), chip.selected("B")) == (3, None)


def test_adg725_en_bit_turns_everything_off_whatever_the_rest():
    driver, chip, device, _ = adg725()
    driver.select(4, 4)
    device.transfer(bytes([0xC5]))  # EIT-kit's "disable" word: EN = 1 wins
    assert (chip.selected("A"), chip.selected("B")) == (None, None)


@pytest.mark.parametrize(("a", "b", "bad"), [(16, None, "16"), (None, -1, "-1"), (1.0, 2, "1.0"), (True, 2, "True")])
def test_adg725_bad_channel_raises_and_sends_nothing(a, b, bad):
    driver, _, _, log = adg725()
    with pytest.raises(ValueError, match=bad):
        driver.select(a, b)
    assert log == []


def test_adg725_two_byte_frame_is_rejected():
    _, _, device, _ = adg725()
    with pytest.raises(EmulatorViolation, match="2 bytes"):
        device.transfer(b"\x23\x00")


def test_adg725_accepts_mode_2_and_rejects_mode_0():
    driver, chip, _, _ = adg725(mode=2)
    driver.select(1, None)
    assert chip.selected("A") == 1
    driver, _, _, _ = adg725(mode=0)
    with pytest.raises(EmulatorViolation, match="mode 0"):
        driver.select(1, None)


def test_adg725_listeners_and_reset():
    driver, chip, _, _ = adg725()
    calls = []
    chip.listeners.append(lambda: calls.append((chip.selected("A"), chip.selected("B"))))
    driver.select(1, 2)
    driver.select(1, None)
    chip.reset()
    assert calls == [(1, None), (1, 2), (None, None)]
    with pytest.raises(ValueError, match="'C'"):
        chip.selected("C")


def test_adg731_select_off_and_emulator_state():
    chip = EmulatedADG731()
    device, log = wire(chip)
    driver = ADG731(device)
    assert chip.selected() is None
    driver.select(31)
    driver.select(0)
    driver.select(0)
    driver.off()
    assert frames(log) == [[0x1F], [0x00], [0x80]]
    assert driver.selection is None and chip.selected() is None
    driver.select(17)
    assert driver.selection == chip.selected() == 17


def test_adg731_chip_select_bit_high_keeps_the_channel():
    chip = EmulatedADG731()
    device, _ = wire(chip)
    device.transfer(bytes([0x05]))
    device.transfer(bytes([0x4A]))
    assert chip.selected() == 5
    device.transfer(bytes([0x20 | 0x0A]))  # bit 5 is don't care
    assert chip.selected() == 10


@pytest.mark.parametrize("channel", [32, -1, None])
def test_adg731_bad_channel_raises(channel):
    chip = EmulatedADG731()
    device, log = wire(chip)
    with pytest.raises(ValueError, match=str(channel)):
        ADG731(device).select(channel)
    assert log == []


def test_adg731_rejects_a_two_byte_frame_and_resets_with_listeners():
    chip = EmulatedADG731()
    device, _ = wire(chip)
    with pytest.raises(EmulatorViolation, match="exactly one"):
        device.transfer(b"\x01\x02")
    calls = []
    chip.listeners.append(lambda: calls.append(chip.selected()))
    device.transfer(bytes([0x03]))
    chip.reset()
    chip.reset()
    assert calls == [3, None]
