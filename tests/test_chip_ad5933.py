"""The AD5933 driver against its register-level emulator: exact transfers, timing, DFT codes and faults.

Expected codes come from the emulator's documented scale: R + jI = 9790 counts
per volt peak at the ADC, rotated by the system phase of 114.35 degrees, so
0.5 V at PGA x1 gives 4895 * (cos 114.35, sin 114.35) = -2018 + 4460j.
"""

import cmath
import errno
import math

import pytest

from appliance.drivers.ad5933 import AD5933
from appliance.drivers.emulated.ad5933 import EmulatedAD5933
from appliance.drivers.emulated.buses import EmulatedI2CBus, EmulatorViolation
from appliance.drivers.emulated.clock import SimulatedClock
from appliance.errors import ChipNotResponding, ChipReadbackMismatch, TransferFailed

MCLK_HZ = 16.776e6
DFT_S = 1024 / (MCLK_HZ / 16)
CODE_50KHZ = 1_600_116  # round(50e3 * 2**27 / (16.776e6 / 4)) = 0x186A74
F_50KHZ = CODE_50KHZ * (MCLK_HZ / 4) / 2**27  # 50000.00077 Hz, the frequency the chip really makes
HALF_VOLT = complex(-2018, 4460)


class Rig:
    """A simulated clock, an I2C bus with an emulated AD5933, and the driver; ``vin`` is set per test."""

    def __init__(self, chip_class=EmulatedAD5933, address=0x0D, **emulator_options):
        self.clock = SimulatedClock()
        self.bus = EmulatedI2CBus(1, self.clock)
        self.vin = 0.5
        self.emulator = chip_class(self.clock, lambda now: self.vin, **emulator_options)
        self.bus.attach(self.emulator)
        self.driver = AD5933(self.bus, self.clock, address=address)

    def configure(self, frequency_hz=50_000, **options):
        settings = {"settling_cycles": 15, "output_range_vpp": 2.0, "pga_gain": 1} | options
        self.driver.configure(frequency_hz, **settings)

    def writes(self, since=0):
        return [list(t.sent) for t in self.bus.log[since:] if t.kind == "i2c-write"]

    def time_of_write(self, sent, since=0):
        [when] = [t.time_s for t in self.bus.log[since:] if t.kind == "i2c-write" and list(t.sent) == sent]
        return when

    def read_registers(self, register, n):
        """Read through the documented pointer protocol, bypassing the driver."""
        self.bus.write_byte_data(0x0D, 0xB0, register)
        return self.bus.write_read(0x0D, bytes([0xA1, n]), n)


@pytest.fixture
def rig():
    return Rig()


def test_frequency_code_is_exact_and_range_checked(rig):
    assert rig.driver.frequency_code(50_000) == CODE_50KHZ
    assert rig.driver.frequency_code(30_000) == 960_070
    assert rig.driver.frequency_code(1_000) == 32_002  # 32002.3 rounded
    for bad in (999.9, 100_000.5, math.nan):
        with pytest.raises(ValueError, match=f"frequency {bad!r} Hz is outside 1000..100000 Hz"):
            rig.driver.frequency_code(bad)
    slow_clock = AD5933(rig.bus, rig.clock, mclk_hz=1e6)
    with pytest.raises(ValueError, match="does not fit 24 bits"):
        slow_clock.frequency_code(100_000)


def test_configure_writes_the_golden_trace(rig):
    rig.configure()
    assert [(t.kind, list(t.sent), t.received) for t in rig.bus.log] == [
        ("i2c-write", [0x82, 0x18], b""), ("i2c-write", [0x83, 0x6A], b""), ("i2c-write", [0x84, 0x74], b""),
        ("i2c-write", [0x85, 0x00], b""), ("i2c-write", [0x86, 0x00], b""), ("i2c-write", [0x87, 0x00], b""),
        ("i2c-write", [0x88, 0x00], b""), ("i2c-write", [0x89, 0x00], b""),
        ("i2c-write", [0x8A, 0x00], b""), ("i2c-write", [0x8B, 0x0F], b""),
        ("i2c-write", [0x80, 0xB1], b""),  # standby, 2 V p-p (00), PGA x1 (1)
        ("i2c-write", [0xB0, 0x82], b""),  # pointer to the start frequency
        ("i2c-write-read", [0xA1, 0x03], b"\x18\x6a\x74"),  # block read of it
    ]
    assert rig.emulator.mode == "standby"
    assert rig.driver.measurement_time_s() == pytest.approx(15 / F_50KHZ + DFT_S, rel=1e-12)
    assert rig.driver.measurement_time_s() == pytest.approx(1.2766333e-3, rel=1e-7)


@pytest.mark.parametrize("cycles, high, low, effective", [
    (511, 0x01, 0xFF, 511), (512, 0x03, 0x00, 512), (1000, 0x03, 0xF4, 1000),
    (1023, 0x07, 0x00, 1024), (2044, 0x07, 0xFF, 2044)])
def test_settling_cycles_beyond_511_use_the_multiplier(rig, cycles, high, low, effective):
    rig.configure(settling_cycles=cycles)
    assert [0x8A, high] in rig.writes() and [0x8B, low] in rig.writes()
    assert rig.driver.measurement_time_s() == pytest.approx(effective / F_50KHZ + DFT_S, rel=1e-12)


@pytest.mark.parametrize("cycles", [2045, -1, 15.0])
def test_settling_cycles_out_of_range_are_refused(rig, cycles):
    with pytest.raises(ValueError, match=f"settling cycles {cycles!r}"):
        rig.configure(settling_cycles=cycles)
    assert rig.bus.log == []


def test_invalid_sweep_settings_are_refused_before_any_write(rig):
    with pytest.raises(ValueError, match="sweep ends at 100500 Hz"):
        rig.configure(90_000, increments=21, increment_hz=500.0)
    with pytest.raises(ValueError, match="increments 512"):
        rig.configure(increments=512)
    with pytest.raises(ValueError, match=r"output range 0\.5 V p-p"):
        rig.configure(output_range_vpp=0.5)
    with pytest.raises(ValueError, match="PGA gain 2"):
        rig.configure(pga_gain=2)
    assert rig.bus.log == []


def test_start_frequency_readback_mismatch_is_raised():
    class StuckBit(EmulatedAD5933):
        """Bit 2 of register 0x84 never sets (a damaged part)."""

        def write(self, data):
            data = bytes(data)
            super().write(data[:1] + bytes([data[1] & 0xFB]) + data[2:] if data[0] == 0x84 else data)

    rig = Rig(StuckBit)
    with pytest.raises(ChipReadbackMismatch, match="written as 0x186A74 read back as 0x186A70"):
        rig.configure()


def test_start_runs_the_documented_sequence_and_the_first_point_needs_no_repeat(rig):
    rig.configure()
    mark = len(rig.bus.log)
    rig.driver.start()
    assert rig.writes(mark) == [[0x80, 0xB1], [0x81, 0x10], [0x80, 0x11], [0x80, 0x21]]
    assert rig.time_of_write([0x80, 0x21], mark) - rig.time_of_write([0x80, 0x11], mark) >= 2e-3
    assert rig.emulator.output_frequency_hz == pytest.approx(F_50KHZ, rel=1e-15)
    measure_mark = len(rig.bus.log)
    assert rig.driver.measure() == HALF_VOLT
    assert [0x80, 0x41] not in rig.writes(measure_mark)
    status_polls = rig.writes(measure_mark).count([0xB0, 0x8F])
    assert status_polls == 1  # it waited the chip's measurement time, then asked once
    data_read = rig.bus.log[-1]
    assert (data_read.kind, list(data_read.sent)) == ("i2c-write-read", [0xA1, 4])
    assert data_read.time_s - rig.time_of_write([0x80, 0x21], mark) >= rig.driver.measurement_time_s()


def test_repeat_measures_a_new_phasor_and_keeps_the_phase_difference(rig):
    rig.configure()
    rig.driver.start()
    first = rig.driver.measure()
    rig.vin = 0.25 * cmath.exp(-1j * math.radians(40))
    mark = len(rig.bus.log)
    second = rig.driver.measure()
    assert (first, second) == (HALF_VOLT, complex(660, 2357))
    assert rig.writes(mark).count([0x80, 0x41]) == 1
    repeat_s = rig.time_of_write([0x80, 0x41], mark)
    assert rig.bus.log[-1].time_s - repeat_s >= rig.driver.measurement_time_s()
    assert math.degrees(cmath.phase(second) - cmath.phase(first)) == pytest.approx(-40.0, abs=0.02)
    assert abs(second) / abs(first) == pytest.approx(0.5, abs=2e-4)


def test_emulator_keeps_the_previous_codes_until_the_dft_is_done(rig):
    rig.configure()
    rig.driver.start()
    rig.driver.measure()
    rig.vin = 0.1
    rig.bus.write_byte_data(0x0D, 0x80, 0x41)  # repeat, behind the driver
    assert rig.read_registers(0x8F, 1) == b"\x74"  # undefined upper bits, sweep complete, no valid data yet
    assert rig.read_registers(0x94, 4) == b"\xf8\x1e\x11\x6c"  # still -2018, 4460
    rig.clock.sleep(rig.driver.measurement_time_s())
    assert rig.read_registers(0x8F, 1) == b"\x76"  # valid data and sweep complete (0 increments)
    assert rig.read_registers(0x94, 4) == b"\xfe\x6c\x03\x7c"  # -404, 892: 0.1 V


def test_emulator_sets_valid_data_after_the_settling_cycles_and_the_dft(rig):
    rig.configure(settling_cycles=1000)  # 500 counted with the x2 multiplier: 20 ms at 50 kHz
    for command in (0xB1, 0x11, 0x21):  # standby, initialise, start sweep
        rig.bus.write_byte_data(0x0D, 0x80, command)
    due_s = rig.clock.monotonic() + 1000 / F_50KHZ + DFT_S
    rig.clock.sleep(due_s - rig.clock.monotonic() - 0.5e-3)
    assert rig.read_registers(0x8F, 1) == b"\x70"  # read about 0.2 ms before it is due
    rig.clock.sleep(due_s - rig.clock.monotonic())
    assert rig.read_registers(0x8F, 1) == b"\x76"


def test_a_chip_reset_behind_the_driver_gives_chip_not_responding(rig):
    rig.configure()
    rig.driver.start()
    rig.driver.measure()
    rig.emulator.reset()
    timeout_s = 1.5 * rig.driver.measurement_time_s() + 5e-3
    before = rig.clock.monotonic()
    with pytest.raises(ChipNotResponding, match=r"AD5933 at 0x0D: no valid data within 6\.91 ms"):
        rig.driver.measure()
    elapsed = rig.clock.monotonic() - before - rig.driver.measurement_time_s()   # it first waits the chip out
    assert timeout_s <= elapsed <= timeout_s + 1e-3
    assert rig.emulator.warnings == ["repeat ignored in power-down"]


def test_smbus_read_byte_data_is_rejected_unless_lenient(rig):
    with pytest.raises(EmulatorViolation, match="read-byte-data of 0x80 is not a documented read"):
        rig.bus.read_byte_data(0x0D, 0x80)
    lenient = Rig(lenient=True)
    assert lenient.bus.read_byte_data(0x0D, 0x80) == 0xA0
    assert lenient.bus.read_block(0x0D, 0x80, 2) == b"\xa0\x00"


def test_a_large_input_clips_and_is_flagged_as_saturated(rig):
    rig.configure()
    rig.driver.start()
    assert not AD5933.is_saturated(rig.driver.measure())
    rig.vin = 2.0  # beyond the ADC's 1.5 V peak: the fundamental of the clipped sine is 1.7114 V
    clipped = rig.driver.measure()
    assert clipped == complex(-6908, 15264)
    assert abs(clipped) < 0.86 * 9790 * 2.0
    assert AD5933.is_saturated(clipped)
    rig.vin = 0.4
    rig.driver.set_pga(5)  # the PGA comes before the ADC: 0.4 V x5 clips the same way
    assert rig.driver.measure() == complex(-6908, 15264)
    assert AD5933.is_saturated(HALF_VOLT, limit=4000)
    assert AD5933.is_saturated(complex(-32768, 3), limit=1e9)


def test_noise_saturates_codes_to_int16():
    rig = Rig(noise_counts=1e6, seed=3)
    rig.configure()
    rig.driver.start()
    z = rig.driver.measure()
    assert {z.real, z.imag} <= {-32768.0, 32767.0}
    assert AD5933.is_saturated(z)


@pytest.mark.parametrize("celsius, raw", [
    (25.0, b"\x03\x20"), (150.0, b"\x12\xc0"), (-12.5, b"\x3e\x70"), (-40.0, b"\x3b\x00")])
def test_temperature_decodes_14_bit_twos_complement(celsius, raw):
    rig = Rig(temperature_c=lambda now: celsius)
    before = rig.clock.monotonic()
    assert rig.driver.temperature_c() == celsius
    assert rig.writes()[0] == [0x80, 0x90]  # measure temperature with the power-on range and PGA x5
    assert rig.bus.log[-1].received == raw
    assert rig.clock.monotonic() - before >= 800e-6


def test_temperature_during_a_sweep_makes_the_next_measure_repeat(rig):
    rig.configure()
    rig.driver.start()
    rig.driver.temperature_c()
    mark = len(rig.bus.log)
    assert rig.driver.measure() == HALF_VOLT
    assert rig.writes(mark)[0] == [0x80, 0x41]


def test_no_acknowledge_at_a_wrong_address_is_transfer_failed():
    rig = Rig(address=0x0E)
    with pytest.raises(TransferFailed, match="address 0x0E: no acknowledge") as caught:
        rig.configure()
    assert caught.value.errno == errno.EREMOTEIO == 121


def test_a_sweep_steps_frequency_and_reports_completion(rig):
    rig.emulator.vin = lambda now: 0.1 * rig.emulator.output_frequency_hz / 10_000
    changes = []
    rig.emulator.listeners.append(lambda: changes.append(rig.emulator.output_frequency_hz))
    rig.configure(30_000, increments=2, increment_hz=10_000.0)
    assert [[0x85, 0x04], [0x86, 0xE2], [0x87, 0x17], [0x88, 0x00], [0x89, 0x02]] == rig.writes()[3:8]
    rig.driver.start()
    readings = [rig.driver.measure()]
    complete = [rig.driver.sweep_complete()]
    for _ in range(2):
        rig.driver.increment()
        readings.append(rig.driver.measure(repeat=False))
        complete.append(rig.driver.sweep_complete())
    assert readings == [complex(-1211, 2676), complex(-1615, 3568), HALF_VOLT]
    assert complete == [False, False, True]
    assert changes == pytest.approx([30_000.01296, 40_000.00687, F_50KHZ], rel=1e-9)
    with pytest.raises(RuntimeError, match="no new point is being measured"):
        rig.driver.measure(repeat=False)


def test_pga_and_range_change_without_restarting_the_sweep(rig):
    rig.vin = 0.1
    rig.configure()
    rig.driver.start()
    assert rig.driver.measure() == complex(-404, 892)
    changes = []
    rig.emulator.listeners.append(lambda: changes.append(rig.emulator.output_vpp))
    mark = len(rig.bus.log)
    rig.driver.set_pga(5)
    rig.driver.set_output_range(0.2)
    assert rig.writes(mark) == [[0x80, 0x00], [0x80, 0x02]]  # no-operation with PGA x5, then 200 mV p-p
    assert (rig.emulator.mode, rig.emulator.pga_gain, rig.emulator.output_vpp) == ("sweeping", 5, 0.198)
    assert changes == [0.198]
    assert rig.driver.measure() == HALF_VOLT  # repeated: 0.1 V x5
    assert [0x80, 0x42] in rig.writes(mark)  # repeat, 200 mV p-p, PGA x5


def test_power_down_stops_the_excitation(rig):
    rig.configure()
    rig.driver.start()
    changes = []
    rig.emulator.listeners.append(lambda: changes.append(rig.emulator.output_frequency_hz))
    rig.driver.power_down()
    assert rig.writes()[-1] == [0x80, 0xA1]
    assert (rig.emulator.mode, rig.emulator.output_frequency_hz, changes) == ("power-down", None, [None])
    with pytest.raises(RuntimeError, match="call start"):
        rig.driver.measure()


def test_driver_refuses_to_start_unconfigured(rig):
    with pytest.raises(RuntimeError, match="configure"):
        rig.driver.start()
    assert rig.bus.log == []


def test_emulator_power_on_state(rig):
    emulator = rig.emulator
    assert rig.read_registers(0x80, 2) == b"\xa0\x00"
    assert rig.read_registers(0x82, 3) == b"\x00\x00\x00"
    assert (emulator.mode, emulator.output_frequency_hz, emulator.pga_gain, emulator.output_vpp) == \
        ("power-down", None, 5, 1.98)


def test_emulator_ignores_writes_to_read_only_registers(rig):
    rig.bus.write_byte_data(0x0D, 0x8F, 0x07)
    rig.bus.write_byte_data(0x0D, 0x94, 0x12)
    assert rig.read_registers(0x8F, 1) == b"\x70"
    assert rig.read_registers(0x94, 1) == b"\x00"
    assert rig.emulator.warnings == ["write of 0x07 to read-only register 0x8F ignored",
                                     "write of 0x12 to read-only register 0x94 ignored"]


@pytest.mark.parametrize("data, message", [
    ([0x80, 0x08], "reserved bits 0x08"), ([0x80, 0x50], "function code 0x5 is reserved"),
    ([0x81, 0x08], "external clock"), ([0x81, 0x01], "reserved bits 0x01"),
    ([0x88, 0x02], "reserved bits 0x02"), ([0x8A, 0x04], "multiplier code 0b10 is reserved"),
    ([0x8C, 0x00], "no register 0x8C"), ([0x80, 0xB1, 0x00], "one byte at a time"),
    ([0xA1, 0x02], "joined to its read"), ([0xB0, 0x90], "no register 0x90")])
def test_emulator_rejects_what_the_chip_forbids(rig, data, message):
    with pytest.raises(EmulatorViolation, match=message):
        rig.bus.write(0x0D, bytes(data))


def test_emulator_reads_need_the_pointer_and_one_byte_plain_reads():
    rig = Rig()
    with pytest.raises(EmulatorViolation, match="pointer was set"):
        rig.bus.read_byte(0x0D)
    rig.bus.write_byte_data(0x0D, 0xB0, 0x80)
    assert [rig.bus.read_byte(0x0D) for _ in range(2)] == [0xA0, 0xA0]  # receive byte does not move the pointer
    with pytest.raises(EmulatorViolation, match="receive byte"):
        rig.bus.read(0x0D, 2)
    with pytest.raises(EmulatorViolation, match="announced 3 bytes but read 2"):
        rig.bus.write_read(0x0D, bytes([0xA1, 3]), 2)


def test_emulator_block_write_from_the_pointer(rig):
    rig.bus.write_byte_data(0x0D, 0xB0, 0x82)
    rig.bus.write(0x0D, bytes([0xA0, 3, 0x18, 0x6A, 0x74]))
    assert rig.read_registers(0x82, 3) == b"\x18\x6a\x74"


def test_emulator_measure_commands_do_nothing_in_standby(rig):
    rig.bus.write_byte_data(0x0D, 0x80, 0xB1)
    for command in (0x21, 0x31, 0x41):
        rig.bus.write_byte_data(0x0D, 0x80, command)
    rig.clock.sleep(0.1)
    assert rig.read_registers(0x8F, 1) == b"\x70"
    assert rig.emulator.output_frequency_hz is None
    assert rig.emulator.warnings == ["start sweep ignored in standby", "increment ignored in standby",
                                     "repeat ignored in standby"]


def test_emulator_reset_returns_to_power_on_and_tells_listeners(rig):
    rig.configure()
    rig.driver.start()
    calls = []
    rig.emulator.listeners.append(lambda: calls.append(rig.emulator.output_frequency_hz))
    rig.emulator.reset()
    assert calls == [None]
    assert rig.emulator.mode == "power-down"
    assert rig.read_registers(0x80, 2) == b"\xa0\x00"
