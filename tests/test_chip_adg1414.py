"""ADG1414 daisy chain and the drive matrix against the chain's emulator: words, order, length, mode, clock."""

import pytest

from appliance.drivers.adg1414 import ADG1414Chain, DriveMatrix
from appliance.drivers.emulated.adg1414 import EmulatedADG1414Chain, drive_of
from appliance.drivers.emulated.buses import BusTiming, EmulatedSPIDevice, EmulatorViolation, FaultPlan
from appliance.drivers.emulated.clock import SimulatedClock


def one_bus_per_electrode(words):
    drive_of(words)


def rig(chips=4, *, mode=1, speed_hz=10_000_000, validate=one_bus_per_electrode):
    log = []
    chip = EmulatedADG1414Chain(chips, validate=validate)
    device = EmulatedSPIDevice("/dev/spidev0.1", mode, speed_hz, chip, SimulatedClock(), BusTiming(), log, FaultPlan())
    return ADG1414Chain(device, chips), chip, log


def test_words_go_out_farthest_chip_first_and_land_on_their_chips():
    driver, chip, log = rig(validate=None)
    driver.write([0x01, 0x02, 0x04, 0x80])
    assert log[-1].sent == bytes([0x80, 0x04, 0x02, 0x01])
    assert chip.words == [0x01, 0x02, 0x04, 0x80]
    assert chip.closed(3, 7) and not chip.closed(3, 6)


def test_the_chain_shifts_its_old_words_out_as_a_read_back():
    driver, chip, log = rig(validate=None)
    driver.write([1, 2, 3, 4])
    assert driver.write([0, 0, 0, 0]) == bytes([4, 3, 2, 1])


def test_a_drive_change_is_one_transfer_and_sets_exactly_two_switches():
    driver, chip, log = rig()
    matrix = DriveMatrix(driver, 16)
    matrix.route(3, 14)
    assert len(log) == 1
    closed = [(c, s) for c in range(4) for s in range(8) if chip.closed(c, s)]
    assert closed == [(0, 4), (3, 3)]                # electrode 3 to I+ (chip 0, j=2), 14 to I- (chip 3, j=1)
    matrix.route(3, 14)
    assert len(log) == 1                             # already routed: nothing sent
    matrix.off()
    assert chip.words == [0, 0, 0, 0]


def test_a_chain_of_the_wrong_length_is_refused():
    driver, chip, log = rig(chips=4)
    short = ADG1414Chain(driver.spi, 3)              # the planted bug: the driver counts one chip too few
    with pytest.raises(EmulatorViolation, match="1 chip"):
        short.write([0, 0, 0])
    with pytest.raises(ValueError, match="takes 4 words"):
        driver.write([0, 0, 0])


def test_an_electrode_on_both_buses_or_two_on_one_bus_is_refused():
    driver, chip, log = rig()
    with pytest.raises(EmulatorViolation, match="both current buses"):
        driver.write([0b11, 0, 0, 0])
    with pytest.raises(EmulatorViolation, match="electrodes 1, 2 all on the I\\+ bus"):
        driver.write([0b0101, 0, 0, 0])
    assert drive_of([0b0001, 0, 0, 0b1000_0000]) == (0, 15) and drive_of([0, 0, 0, 0]) == (None, None)
    assert chip.words == [0, 0, 0, 0]                # nothing latched
    matrix = DriveMatrix(driver, 16)
    with pytest.raises(ValueError, match="both buses"):
        matrix.route(5, 5)
    with pytest.raises(ValueError, match="1..16"):
        matrix.route(0, 17)


@pytest.mark.parametrize("mode", [0, 3])
def test_modes_that_sample_on_the_rising_edge_are_refused(mode):
    driver, chip, log = rig(mode=mode)
    with pytest.raises(EmulatorViolation, match="SPI mode"):
        driver.off()


def test_a_chain_is_limited_by_sdo_delay_but_one_chip_is_not():
    driver, chip, log = rig(chips=4, speed_hz=20_000_000)
    with pytest.raises(EmulatorViolation, match="exceeds"):
        driver.off()
    driver, chip, log = rig(chips=1, speed_hz=40_000_000)
    driver.off()
    assert ADG1414Chain.speed_limit_hz(1) == 50_000_000 and ADG1414Chain.speed_limit_hz(128) == 11_000_000


def test_power_on_state_and_reset():
    driver, chip, log = rig()
    assert chip.words == [0, 0, 0, 0]
    driver.write([0, 0, 0, 0x10])
    changes = []
    chip.listeners.append(lambda: changes.append(1))
    chip.reset()
    assert chip.words == [0, 0, 0, 0] and changes == [1]


def test_bad_words_are_refused_before_anything_is_sent():
    driver, chip, log = rig()
    with pytest.raises(ValueError, match="not 0..255"):
        driver.write([0, 0, 256, 0])
    assert log == []
    with pytest.raises(ValueError, match="switch 16 electrodes, not 20"):
        DriveMatrix(driver, 20)
