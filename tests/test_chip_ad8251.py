"""AD8251 driver against its emulator: the gain latches on a /WR falling edge and on nothing else."""

import pytest

from appliance.drivers.ad8251 import AD8251
from appliance.drivers.emulated.ad8251 import EmulatedAD8251
from appliance.drivers.emulated.buses import BusTiming, EmulatedGPIOLines, EmulatorViolation, GPIOBank
from appliance.drivers.emulated.clock import SimulatedClock

LINES = {"a0": "GPIO5", "a1": "GPIO6", "wr": "GPIO13"}
A0, A1, WR = LINES["a0"], LINES["a1"], LINES["wr"]


def wire(timing=None):
    """(driver, emulator, lines, bank) with the lines requested as the driver asks."""
    bank = GPIOBank(SimulatedClock(), ["GPIO5", "GPIO6", "GPIO13", "GPIO19"], [])
    chip = EmulatedAD8251(bank, **LINES)
    lines = EmulatedGPIOLines(bank, AD8251.line_request(**LINES), "pga", timing or BusTiming())
    return AD8251(lines, **LINES), chip, lines, bank


def test_line_request_gives_outputs_with_wr_high():
    request = AD8251.line_request(**LINES)
    assert dict(request.outputs) == {A0: 0, A1: 0, WR: 1}
    assert dict(request.inputs) == {}


def test_power_up_gain_is_one_and_requesting_the_lines_latches_nothing():
    driver, chip, _, _ = wire()
    assert driver.gain == chip.gain == 1
    assert chip.latches == []


@pytest.mark.parametrize(("gain", "a1", "a0"), [(1, 0, 0), (2, 0, 1), (4, 1, 0), (8, 1, 1)])
def test_every_gain_latches(gain, a1, a0):
    driver, chip, lines, bank = wire()
    driver.set_gain(8 if gain != 8 else 2)
    driver.set_gain(gain)
    assert chip.gain == driver.gain == gain
    assert lines.get_values([A1, A0, WR]) == {A1: a1, A0: a0, WR: 1}
    assert [g for _, g in chip.latches][-1] == gain
    setup, fall, rise = bank.log[-3:]
    assert (setup.target, fall.target, rise.target) == (f"{A1},{A0},{WR}", WR, WR)
    assert [list(setup.sent), list(fall.sent), list(rise.sent)] == [[a1, a0, 1], [0], [1]]
    assert chip.latches[-1][0] == fall.time_s


def test_changing_a0_a1_without_a_wr_edge_keeps_the_gain():
    driver, chip, lines, _ = wire()
    driver.set_gain(4)
    lines.set_values({A0: 1, A1: 1})
    lines.set_values({A0: 0, A1: 0})
    lines.set_values({A0: 1})
    assert chip.gain == 4
    assert len(chip.latches) == 1


def test_a_wr_rising_edge_does_not_latch():
    _, chip, lines, _ = wire()
    lines.set_values({WR: 0})  # falling edge with A1A0 = 00: latches gain 1
    lines.set_values({A0: 1, A1: 1})
    lines.set_values({WR: 1})  # rising edge: no latch
    assert chip.gain == 1
    assert [g for _, g in chip.latches] == [1]


def test_address_set_after_the_wr_edge_leaves_the_old_gain():
    driver, chip, lines, _ = wire()
    driver.set_gain(2)
    lines.set_values({WR: 0})  # latches A1A0 = 01 again
    lines.set_values({A1: 1, A0: 1})  # too late for this edge
    lines.set_values({WR: 1})
    assert chip.gain == 2
    assert [g for _, g in chip.latches] == [2, 2]


@pytest.mark.parametrize("values", [{A1: 1, A0: 1, WR: 0}, {WR: 0, A1: 1}])
def test_address_changed_in_the_same_call_as_the_edge_is_a_violation(values):
    _, _, lines, _ = wire()
    with pytest.raises(EmulatorViolation, match="setup time"):
        lines.set_values(values)


def test_separate_calls_are_not_simultaneous_even_with_zero_call_time():
    driver, chip, _, bank = wire(BusTiming(call_overhead_s=0.0))
    driver.set_gain(4)
    assert chip.gain == 4
    assert bank.clock.monotonic() == 0.0


@pytest.mark.parametrize("gain", [0, 3, 5, 10, 8.5])
def test_gain_not_offered_raises_and_drives_nothing(gain):
    driver, _, _, bank = wire()
    with pytest.raises(ValueError, match=repr(gain)):
        driver.set_gain(gain)
    assert bank.log == []
    assert driver.gain == 1


def test_driver_refuses_lines_it_was_not_given():
    _, _, lines, _ = wire()
    with pytest.raises(ValueError, match="GPIO19"):
        AD8251(lines, a0=A0, a1=A1, wr="GPIO19")


def test_listeners_and_reset():
    driver, chip, _, _ = wire()
    calls = []
    chip.listeners.append(lambda: calls.append(chip.gain))
    driver.set_gain(8)
    driver.set_gain(8)
    chip.reset()
    assert calls == [8, 1]
    assert chip.gain == 1
    assert len(chip.latches) == 2
