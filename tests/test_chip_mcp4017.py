"""MCP4017 driver against its emulator: send-byte write, receive-byte read-back, and the errors."""

import errno

import pytest

from appliance.drivers.emulated.buses import EmulatedI2CBus
from appliance.drivers.emulated.clock import SimulatedClock
from appliance.drivers.emulated.mcp4017 import EmulatedMCP4017
from appliance.drivers.mcp4017 import MCP4017
from appliance.errors import ChipReadbackMismatch, TransferFailed


def wire(chip=None):
    bus = EmulatedI2CBus(1, SimulatedClock())
    chip = chip or EmulatedMCP4017()
    bus.attach(chip)
    return MCP4017(bus), chip, bus


def test_set_wiper_golden_trace():
    driver, chip, bus = wire()
    driver.set_wiper(0x40)
    assert [(t.kind, t.target, t.sent, t.received) for t in bus.log] == [
        ("i2c-write", "i2c1@0x2F", b"\x40", b""),
        ("i2c-read", "i2c1@0x2F", b"", b"\x40"),
    ]
    assert chip.wiper == 0x40


def test_power_on_wiper_is_mid_scale():
    driver, chip, _ = wire()
    assert driver.wiper() == chip.wiper == 0x3F
    chip.wiper = 0
    chip.reset()
    assert driver.wiper() == 0x3F


@pytest.mark.parametrize("position", [0, 1, 63, 126, 127])
def test_every_edge_position_round_trips(position):
    driver, chip, _ = wire()
    driver.set_wiper(position)
    assert chip.wiper == driver.wiper() == position


class StuckMCP4017(EmulatedMCP4017):
    """A chip whose wiper register ignores writes (a damaged part, or another chip at 0x2F)."""

    def write(self, data: bytes) -> None:
        pass


def test_readback_mismatch_names_address_written_and_read():
    driver, _, _ = wire(StuckMCP4017())
    with pytest.raises(ChipReadbackMismatch, match=r"0x2F.*wrote wiper 100, read back 63"):
        driver.set_wiper(100)


def test_no_chip_at_the_address_gives_errno_121():
    _, _, bus = wire()
    driver = MCP4017(bus, address=0x2E)
    with pytest.raises(TransferFailed) as caught:
        driver.set_wiper(10)
    assert caught.value.errno == errno.EREMOTEIO == 121
    assert "0x2E" in str(caught.value)


@pytest.mark.parametrize("position", [-1, 128, 255, 12.0, True])
def test_position_out_of_range_raises_and_sends_nothing(position):
    driver, _, bus = wire()
    with pytest.raises(ValueError, match=repr(position)):
        driver.set_wiper(position)
    assert bus.log == []


def test_emulator_ignores_the_msb_and_keeps_the_last_of_several_bytes():
    _, chip, bus = wire()
    bus.write(0x2F, b"\xC0")
    assert chip.wiper == 0x40
    bus.write(0x2F, b"\x10\x20\x7F")
    assert chip.wiper == 0x7F
    assert bus.read(0x2F, 2) == b"\x7F\x7F"


def test_listeners_are_told_of_changes_only():
    driver, chip, _ = wire()
    calls = []
    chip.listeners.append(lambda: calls.append(chip.wiper))
    driver.set_wiper(0x3F)
    driver.set_wiper(5)
    chip.reset()
    assert calls == [5, 0x3F]
