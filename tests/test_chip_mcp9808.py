"""MCP9808 driver against its emulator: identity, sign decoding, quantisation and conversion timing."""

import pytest

from appliance.drivers.emulated.buses import EmulatedI2CBus, EmulatorViolation
from appliance.drivers.emulated.clock import SimulatedClock
from appliance.drivers.emulated.mcp9808 import EmulatedMCP9808
from appliance.drivers.mcp9808 import MCP9808
from appliance.errors import ChipReadbackMismatch

CONVERSION_S = 0.25


def wire(temperature_c=lambda t: 23.5625):
    clock = SimulatedClock()
    bus = EmulatedI2CBus(1, clock)
    chip = EmulatedMCP9808(clock, temperature_c)
    bus.attach(chip)
    return MCP9808(bus), chip, bus, clock


def test_identity_check_passes_and_gives_the_revision():
    driver, _, bus, _ = wire()
    assert driver.check_identity() == 0x00
    assert [(t.kind, t.sent) for t in bus.log] == [("i2c-write-read", b"\x06"), ("i2c-write-read", b"\x07")]


@pytest.mark.parametrize(("attribute", "value", "message"), [
    ("device_revision", 0x7500, "device ID 0x75"),
    ("manufacturer_id", 0x0041, "manufacturer ID 0x0041"),
])
def test_identity_check_fails_against_another_chip(attribute, value, message):
    driver, chip, _, _ = wire()
    setattr(chip, attribute, value)
    with pytest.raises(ChipReadbackMismatch, match=message):
        driver.check_identity()


@pytest.mark.parametrize(("true_c", "raw"), [(23.5625, b"\xC1\x79"), (-5.25, b"\x3F\xAC"), (0.0, b"\x80\x00")])
def test_temperatures_decode_exactly_with_the_alert_flags_masked(true_c, raw):
    driver, _, bus, clock = wire(lambda t: true_c)
    clock.sleep(CONVERSION_S)
    # limits are 0 degC at power-on: 23.5625 > T_UPPER and >= T_CRIT sets bits 15 and 14;
    # -5.25 < T_LOWER sets bit 13 (0x2000) over code -84, 13-bit two's complement 0x2000 - 84 = 0x1FAC
    assert bus.read_block(0x18, 0x05, 2) == raw
    assert driver.temperature_c() == true_c


@pytest.mark.parametrize(("true_c", "read_c"), [(23.6, 23.5625), (23.6249, 23.5625), (23.625, 23.625),
                                                (-5.26, -5.3125), (300.0, 255.9375), (-300.0, -256.0)])
def test_quantisation_floors_to_a_sixteenth_and_saturates(true_c, read_c):
    driver, _, _, clock = wire(lambda t: true_c)
    clock.sleep(CONVERSION_S)
    assert driver.temperature_c() == read_c


def test_lower_resolution_quantises_coarser_and_converts_faster():
    driver, _, bus, clock = wire(lambda t: 23.6)
    bus.write(0x18, b"\x08\x00")  # 0.5 degC, t_conv 30 ms
    clock.sleep(0.030)
    assert driver.temperature_c() == 23.5


def test_read_before_the_first_conversion_gives_the_power_on_zero():
    driver, _, _, clock = wire(lambda t: 31.25)
    assert driver.temperature_c() == 0.0
    clock.sleep(CONVERSION_S - 0.001)
    assert driver.temperature_c() == 0.0
    clock.sleep(0.001)
    assert driver.temperature_c() == 31.25


def test_register_holds_the_last_completed_conversion():
    driver, _, _, clock = wire(lambda t: 20.0 + t)  # 1 degC per second
    clock.sleep(1.3)
    assert driver.temperature_c() == 21.25  # the conversion that completed at 1.25 s
    clock.sleep(0.1)
    assert driver.temperature_c() == 21.25  # about 1.40 s: nothing has completed since 1.25 s
    clock.sleep(0.1)
    assert driver.temperature_c() == 21.5  # about 1.50 s: the next one has


def test_writable_registers_and_read_only_writes_ignored_with_a_note():
    _, chip, bus, _ = wire()
    bus.write(0x18, b"\x02\x01\x94")  # T_UPPER = +25.25 degC
    assert bus.read_block(0x18, 0x02, 2) == b"\x01\x94"
    bus.write(0x18, b"\x06\x12\x34")
    assert bus.read_block(0x18, 0x06, 2) == b"\x00\x54"
    assert len(chip.warnings) == 1 and "0x06" in chip.warnings[0]


def test_shutdown_holds_the_last_value():
    driver, _, bus, clock = wire(lambda t: 20.0 + t)
    clock.sleep(0.5)
    bus.write(0x18, b"\x01\x01\x00")  # SHDN
    clock.sleep(2.0)
    assert driver.temperature_c() == 20.5
    bus.write(0x18, b"\x01\x00\x00")
    assert driver.temperature_c() == 20.5  # conversions restart: none completed yet
    clock.sleep(CONVERSION_S)
    assert driver.temperature_c() == pytest.approx(20.0 + clock.monotonic(), abs=1 / 16)


@pytest.mark.parametrize("data", [b"\x10", b"\x09", b"\x01\x00", b"\x08\x00\x03"])
def test_bad_pointer_or_length_is_a_violation(data):
    _, _, bus, _ = wire()
    with pytest.raises(EmulatorViolation):
        bus.write(0x18, data)
