"""The Linux buses (spidev, smbus2, gpiod) against recording doubles, and against the real libraries without hardware.

The doubles stand in for the library objects with the same signatures: they
record every call with its arguments and return scripted values or raise
scripted OSErrors, so each test states the exact calls a bus operation makes.
The GPIO double uses gpiod's real ``LineSettings`` and enums, so the settings
the backend builds are checked against the library's own types.
"""

import errno
import functools
import glob
from dataclasses import dataclass
from datetime import timedelta
from types import SimpleNamespace

import pytest

from appliance.drivers import linux_gpio, linux_i2c, linux_spi
from appliance.drivers.bus import FALLING, PULL_UP, RISING, Clock, LineRequest
from appliance.drivers.linux_board import LinuxBoard
from appliance.drivers.linux_gpio import LinuxGPIOLines, find_line_chips, gpiochip_paths
from appliance.drivers.linux_i2c import LinuxI2CBus
from appliance.drivers.linux_spi import LinuxSPIDevice
from appliance.errors import BackendUnavailable, BusError, BusInUse, DeviceMissing, TransferFailed


class Recorder:
    """Every call as ``(method, *args)`` (plus a dict of keywords if any); outcomes scripted per method."""

    def __init__(self):
        self.calls = []
        self.script = {}

    def will(self, method, *outcomes):
        """The next calls of ``method`` return (or raise, for an exception) ``outcomes`` in turn."""
        self.script.setdefault(method, []).extend(outcomes)

    def record(self, method, *args, **kwargs):
        self.calls.append((method, *args, kwargs) if kwargs else (method, *args))
        queue = self.script.get(method)
        outcome = queue.pop(0) if queue else None
        if isinstance(outcome, BaseException):
            raise outcome
        return outcome

    def named(self, *methods):
        return [call for call in self.calls if call[0] in methods]


# --- SPI --------------------------------------------------------------------------------------------------

class FakeSpiDev:
    """spidev.SpiDev: open, attribute writes, xfer2 and close are recorded."""

    def __init__(self, rec, bus=None, device=None):
        object.__setattr__(self, "_rec", rec)
        rec.record("SpiDev")

    def __setattr__(self, name, value):
        self._rec.record("set", name, value)

    def open(self, bus, device):
        self._rec.record("open", bus, device)

    def xfer2(self, values, speed_hz=0, delay_usecs=0, bits_per_word=0):
        return self._rec.record("xfer2", values)

    def close(self):
        self._rec.record("close")


@pytest.fixture
def spi(monkeypatch):
    rec = Recorder()
    monkeypatch.setattr(linux_spi, "spidev", SimpleNamespace(SpiDev=functools.partial(FakeSpiDev, rec)))
    return rec


def test_spi_transfer_is_one_xfer2_after_mode_and_speed(spi):
    spi.will("xfer2", [0xAA, 0x55, 0x00])
    device = LinuxSPIDevice(0, 1, mode=1, max_speed_hz=2_000_000)
    assert device.transfer(b"\x01\x02\x03") == b"\xaa\x55\x00"
    assert spi.calls == [("SpiDev",), ("open", 0, 1), ("set", "mode", 1), ("set", "max_speed_hz", 2_000_000),
                         ("set", "bits_per_word", 8), ("xfer2", [1, 2, 3])]
    assert type(spi.calls[-1][1]) is list
    assert (device.name, device.mode, device.max_speed_hz) == ("/dev/spidev0.1", 1, 2_000_000)


def test_spi_io_error_is_transfer_failed_naming_the_device(spi):
    spi.will("xfer2", OSError(errno.EIO, "Input/output error"))
    device = LinuxSPIDevice(0, 1, mode=0, max_speed_hz=1_000_000)
    with pytest.raises(TransferFailed, match=r"/dev/spidev0\.1") as caught:
        device.transfer(b"\x00")
    assert caught.value.errno == errno.EIO


def test_spi_missing_node_is_device_missing_with_a_hint(spi):
    spi.will("open", FileNotFoundError(errno.ENOENT, "No such file or directory"))
    with pytest.raises(DeviceMissing) as caught:
        LinuxSPIDevice(1, 2, mode=0, max_speed_hz=1_000_000)
    assert "/dev/spidev1.2" in str(caught.value)
    assert "dtparam=spi=on" in str(caught.value) and "overlay" in str(caught.value)
    assert isinstance(caught.value, FileNotFoundError)


def test_spi_permission_denied_names_the_spi_group(spi):
    spi.will("open", PermissionError(errno.EACCES, "Permission denied"))
    with pytest.raises(BusError, match=r"/dev/spidev0\.0: permission denied.*spi group") as caught:
        LinuxSPIDevice(0, 0, mode=0, max_speed_hz=1_000_000)
    assert not isinstance(caught.value, TransferFailed)


def test_spi_refused_mode_closes_the_device(spi):
    spi.will("set", OSError(errno.EINVAL, "Invalid argument"))
    with pytest.raises(TransferFailed, match=r"/dev/spidev0\.0"):
        LinuxSPIDevice(0, 0, mode=3, max_speed_hz=1_000_000)
    assert spi.calls[-1] == ("close",)


def test_spi_close_is_idempotent_and_final(spi):
    device = LinuxSPIDevice(0, 0, mode=0, max_speed_hz=1_000_000)
    device.close()
    device.close()
    assert spi.named("close") == [("close",)]
    with pytest.raises(BusError, match="after close"):
        device.transfer(b"\x00")
    assert spi.named("xfer2") == []


def test_spi_without_spidev_is_backend_unavailable(monkeypatch):
    monkeypatch.setattr(linux_spi, "spidev", None)
    with pytest.raises(BackendUnavailable, match="pip install spidev") as caught:
        LinuxSPIDevice(0, 0, mode=0, max_speed_hz=1_000_000)
    assert isinstance(caught.value, ImportError)


# --- I2C --------------------------------------------------------------------------------------------------

@dataclass
class Message:
    """smbus2.i2c_msg: ``bytes()`` of it is its data."""

    kind: str
    address: int
    data: bytes

    def __bytes__(self):
        return self.data


class FakeI2CMsg:
    @staticmethod
    def write(address, buf):
        return Message("write", address, bytes(buf))

    @staticmethod
    def read(address, length):
        return Message("read", address, bytes(length))


class FakeSMBus:
    """smbus2.SMBus: i2c_rdwr records its messages and fills the read message with the scripted bytes."""

    rec: Recorder

    def __init__(self, bus=None, force=False):
        self.rec.record("SMBus", bus)

    def i2c_rdwr(self, *i2c_msgs):
        reply = self.rec.record("i2c_rdwr", *[(m.kind, m.address, m.data if m.kind == "write" else len(m.data))
                                              for m in i2c_msgs])
        for message in i2c_msgs:
            if message.kind == "read":
                message.data = reply

    def __getattr__(self, method):
        if method not in ("write_byte", "read_byte", "write_byte_data", "read_byte_data", "write_word_data",
                          "read_word_data", "write_i2c_block_data", "read_i2c_block_data", "close"):
            raise AttributeError(method)
        return functools.partial(self.rec.record, method)


@pytest.fixture
def i2c(monkeypatch):
    rec = Recorder()
    monkeypatch.setattr(linux_i2c, "SMBus", type("SMBus", (FakeSMBus,), {"rec": rec}))
    monkeypatch.setattr(linux_i2c, "i2c_msg", FakeI2CMsg)
    return rec


def test_i2c_primitives_are_i2c_rdwr_transactions(i2c):
    i2c.will("i2c_rdwr", None, b"\x12\x34", b"\x56")
    bus = LinuxI2CBus(1)
    bus.write(0x48, b"\x01\x84\x83")
    assert bus.read(0x48, 2) == b"\x12\x34"
    assert bus.write_read(0x0D, b"\xb0", 1) == b"\x56"
    assert i2c.calls == [("SMBus", 1),
                         ("i2c_rdwr", ("write", 0x48, b"\x01\x84\x83")),
                         ("i2c_rdwr", ("read", 0x48, 2)),
                         ("i2c_rdwr", ("write", 0x0D, b"\xb0"), ("read", 0x0D, 1))]
    assert bus.name == "/dev/i2c-1"


@pytest.mark.parametrize("method, args, reply, expected_call, result", [
    ("write_byte", (0x2F, 0x40), None, ("write_byte", 0x2F, 0x40), None),
    ("read_byte", (0x2F,), 0x40, ("read_byte", 0x2F), 0x40),
    ("write_byte_data", (0x0D, 0x80, 0x10), None, ("write_byte_data", 0x0D, 0x80, 0x10), None),
    ("read_byte_data", (0x0D, 0x8F), 0x04, ("read_byte_data", 0x0D, 0x8F), 0x04),
    ("write_word_swapped", (0x48, 0x01, 0x8583), None, ("write_word_data", 0x48, 0x01, 0x8385), None),
    ("read_word_swapped", (0x18, 0x06), 0x5400, ("read_word_data", 0x18, 0x06), 0x0054),
    ("write_block", (0x0D, 0x82, b"\x01\x02\x03"), None, ("write_i2c_block_data", 0x0D, 0x82, [1, 2, 3]), None),
    ("read_block", (0x0D, 0x94, 4), [1, 2, 3, 4], ("read_i2c_block_data", 0x0D, 0x94, 4), b"\x01\x02\x03\x04"),
])
def test_i2c_helpers_use_the_native_smbus_calls(i2c, method, args, reply, expected_call, result):
    i2c.will(expected_call[0], reply)
    bus = LinuxI2CBus(1)
    assert getattr(bus, method)(*args) == result
    assert i2c.calls == [("SMBus", 1), expected_call]


def test_i2c_blocks_beyond_32_bytes_are_plain_transactions(i2c):
    i2c.will("i2c_rdwr", None, bytes(range(40)))
    bus = LinuxI2CBus(1)
    bus.write_block(0x50, 0x10, bytes(33))
    assert bus.read_block(0x50, 0x20, 40) == bytes(range(40))
    assert i2c.calls[1:] == [("i2c_rdwr", ("write", 0x50, b"\x10" + bytes(33))),
                             ("i2c_rdwr", ("write", 0x50, b"\x20"), ("read", 0x50, 40))]


@pytest.mark.parametrize("method, args, library_call", [
    ("write_read", (0x48, b"\x00", 2), "i2c_rdwr"),
    ("read_byte_data", (0x48, 0x00), "read_byte_data"),
])
def test_i2c_no_acknowledge_is_transfer_failed_121_naming_bus_and_address(i2c, method, args, library_call):
    i2c.will(library_call, OSError(errno.EREMOTEIO, "Remote I/O error"))
    bus = LinuxI2CBus(1)
    with pytest.raises(TransferFailed) as caught:
        getattr(bus, method)(*args)
    assert caught.value.errno == 121
    assert "I2C bus 1 address 0x48" in str(caught.value)


def test_i2c_address_claimed_by_a_kernel_driver_is_bus_in_use(i2c):
    i2c.will("write_byte", OSError(errno.EBUSY, "Device or resource busy"))
    with pytest.raises(BusInUse, match="I2C bus 1 address 0x2F"):
        LinuxI2CBus(1).write_byte(0x2F, 0x7F)


def test_i2c_missing_adapter_is_device_missing_with_a_hint(i2c):
    i2c.will("SMBus", FileNotFoundError(errno.ENOENT, "No such file or directory"))
    with pytest.raises(DeviceMissing, match=r"/dev/i2c-3 does not exist.*dtparam=i2c_arm=on"):
        LinuxI2CBus(3)


def test_i2c_close_is_idempotent_and_final(i2c):
    bus = LinuxI2CBus(1)
    bus.close()
    bus.close()
    assert i2c.named("close") == [("close",)]
    with pytest.raises(BusError, match="after close"):
        bus.read_byte(0x48)


def test_i2c_without_smbus2_is_backend_unavailable(monkeypatch):
    monkeypatch.setattr(linux_i2c, "SMBus", None)
    with pytest.raises(BackendUnavailable, match="pip install smbus2"):
        LinuxI2CBus(1)


# --- GPIO -------------------------------------------------------------------------------------------------

class FakeGpiod:
    """The gpiod module: chips are ``{path: {line name: offset}}``; real LineSettings and enums."""

    def __init__(self, real, chips, version="2.5.0"):
        self.__version__, self.line = version, real.line
        self.LineSettings, self.EdgeEvent = real.LineSettings, real.EdgeEvent
        self.chips, self.rec = chips, Recorder()

    def is_gpiochip_device(self, path):
        self.rec.record("is_gpiochip_device", path)
        return path in self.chips

    def Chip(self, path):
        self.rec.record("Chip", path)
        if path not in self.chips:
            raise FileNotFoundError(errno.ENOENT, "No such file or directory")
        return FakeChip(self, path)

    def request_lines(self, path, config, consumer=None, event_buffer_size=None, output_values=None):
        self.rec.record("request_lines", path, config, consumer=consumer)
        return FakeLineRequest(self.rec, path)

    def event(self, offset):
        return self.EdgeEvent(self.EdgeEvent.Type.RISING_EDGE, 0, offset, 0, 0)


class FakeChip:
    def __init__(self, gpiod, path):
        self.gpiod, self.path = gpiod, path

    def line_offset_from_id(self, name):
        self.gpiod.rec.record("line_offset_from_id", self.path, name)
        if name not in self.gpiod.chips[self.path]:
            raise OSError(errno.ENOENT, "No such file or directory")
        return self.gpiod.chips[self.path][name]

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.gpiod.rec.record("close", self.path)


class FakeLineRequest:
    def __init__(self, rec, path):
        self.rec, self.path = rec, path

    def set_values(self, values):
        self.rec.record("set_values", self.path, values)

    def get_values(self, lines=None):
        return self.rec.record("get_values", self.path, lines)

    def wait_edge_events(self, timeout=None):
        return self.rec.record("wait_edge_events", self.path, timeout)

    def read_edge_events(self, max_events=None):
        return self.rec.record("read_edge_events", self.path)

    def release(self):
        self.rec.record("release", self.path)


@pytest.fixture
def gpio(monkeypatch, tmp_path):
    """Two chips in a scratch /dev: gpiochip0 with GPIO2/GPIO3, gpiochip1 with GPIO17/GPIO27."""
    real = pytest.importorskip("gpiod")
    chip0, chip1 = str(tmp_path / "gpiochip0"), str(tmp_path / "gpiochip1")
    for path in (chip0, chip1):
        open(path, "w").close()
    fake = FakeGpiod(real, {chip0: {"GPIO2": 2, "GPIO3": 3}, chip1: {"GPIO17": 17, "GPIO27": 27}})
    monkeypatch.setattr(linux_gpio, "gpiod", fake)
    monkeypatch.setattr(linux_gpio, "gpiochip_paths", functools.partial(gpiochip_paths, str(tmp_path)))
    return SimpleNamespace(fake=fake, rec=fake.rec, chip0=chip0, chip1=chip1, line=real.line,
                           settings=real.LineSettings)


def test_gpiochip_paths_lists_chip_devices_in_number_order(gpio, tmp_path):
    for name in ("gpiochip10", "gpiochip2", "gpiochip3"):
        open(tmp_path / name, "w").close()
    gpio.fake.chips.update({str(tmp_path / "gpiochip10"): {}, str(tmp_path / "gpiochip2"): {}})
    assert gpiochip_paths(str(tmp_path)) == [str(tmp_path / n) for n in ("gpiochip0", "gpiochip1", "gpiochip2",
                                                                           "gpiochip10")]
    assert len(gpio.rec.named("is_gpiochip_device")) == 5


def test_a_line_on_the_second_chip_is_found_there(gpio):
    assert find_line_chips(["GPIO17"]) == {"GPIO17": gpio.chip1}
    assert gpio.rec.named("Chip", "line_offset_from_id", "close") == [
        ("Chip", gpio.chip0), ("line_offset_from_id", gpio.chip0, "GPIO17"), ("close", gpio.chip0),
        ("Chip", gpio.chip1), ("line_offset_from_id", gpio.chip1, "GPIO17"), ("close", gpio.chip1)]


def test_the_search_stops_once_every_line_is_found(gpio):
    assert find_line_chips(["GPIO3", "GPIO2"]) == {"GPIO3": gpio.chip0, "GPIO2": gpio.chip0}
    assert ("Chip", gpio.chip1) not in gpio.rec.calls


def test_a_line_on_no_chip_is_device_missing_naming_line_and_chips(gpio):
    with pytest.raises(DeviceMissing) as caught:
        find_line_chips(["GPIO17", "GPIO99"])
    assert "GPIO99" in str(caught.value) and gpio.chip0 in str(caught.value) and gpio.chip1 in str(caught.value)


def test_no_gpio_chip_at_all_is_device_missing(gpio, monkeypatch):
    monkeypatch.setattr(linux_gpio, "gpiochip_paths", list)
    with pytest.raises(DeviceMissing, match="GPIO line GPIO17: no GPIO chip exists"):
        find_line_chips(["GPIO17"])


def test_a_configured_chip_path_skips_the_scan(gpio):
    LinuxGPIOLines(LineRequest({"GPIO17": 0}, {}), consumer="mux", chip_path=gpio.chip1)
    assert gpio.rec.named("is_gpiochip_device") == [] and gpio.rec.named("Chip") == [("Chip", gpio.chip1)]
    with pytest.raises(DeviceMissing, match="gpiochip7"):
        LinuxGPIOLines(LineRequest({"GPIO17": 0}, {}), consumer="mux", chip_path=gpio.chip1[:-1] + "7")


def test_lines_on_two_chips_make_one_request_each(gpio):
    line, settings = gpio.line, gpio.settings
    LinuxGPIOLines(LineRequest({"GPIO2": 1, "GPIO17": 0}, {"GPIO27": RISING, "GPIO3": FALLING}), consumer="ad5933")
    assert gpio.rec.named("request_lines") == [
        ("request_lines", gpio.chip0,
         {2: settings(direction=line.Direction.OUTPUT, output_value=line.Value.ACTIVE),
          3: settings(direction=line.Direction.INPUT, edge_detection=line.Edge.FALLING)}, {"consumer": "ad5933"}),
        ("request_lines", gpio.chip1,
         {17: settings(direction=line.Direction.OUTPUT, output_value=line.Value.INACTIVE),
          27: settings(direction=line.Direction.INPUT, edge_detection=line.Edge.RISING)}, {"consumer": "ad5933"})]


def test_an_input_without_edge_has_no_edge_detection(gpio):
    line = gpio.line
    LinuxGPIOLines(LineRequest({}, {"GPIO2": None}), consumer="button")
    assert gpio.rec.named("request_lines")[0][2] == {
        2: gpio.settings(direction=line.Direction.INPUT, edge_detection=line.Edge.NONE)}


def test_an_input_for_an_open_drain_output_is_requested_with_the_pull_up(gpio):
    line = gpio.line
    LinuxGPIOLines(LineRequest({}, {"GPIO27": FALLING}, bias={"GPIO27": PULL_UP}), consumer="adc")
    assert gpio.rec.named("request_lines")[0][2] == {
        27: gpio.settings(direction=line.Direction.INPUT, edge_detection=line.Edge.FALLING, bias=line.Bias.PULL_UP)}


def test_a_bias_is_for_inputs_and_is_a_pull_up_or_down():
    with pytest.raises(ValueError, match="GPIO17: a bias is for inputs"):
        LineRequest({"GPIO17": 0}, {}, bias={"GPIO17": PULL_UP})
    with pytest.raises(ValueError, match="GPIO27: bias must be one of"):
        LineRequest({}, {"GPIO27": FALLING}, bias={"GPIO27": "up"})


def test_set_values_touches_each_chip_once(gpio):
    value = gpio.line.Value
    lines = LinuxGPIOLines(LineRequest({"GPIO2": 0, "GPIO3": 0, "GPIO17": 0}, {}), consumer="mux")
    lines.set_values({"GPIO2": 1, "GPIO17": 1, "GPIO3": 0})
    assert gpio.rec.named("set_values") == [("set_values", gpio.chip0, {2: value.ACTIVE, 3: value.INACTIVE}),
                                            ("set_values", gpio.chip1, {17: value.ACTIVE})]


def test_set_values_refuses_inputs_and_unknown_lines(gpio):
    lines = LinuxGPIOLines(LineRequest({"GPIO2": 0}, {"GPIO3": FALLING}), consumer="mux")
    with pytest.raises(ValueError, match="GPIO3 of mux is an input"):
        lines.set_values({"GPIO3": 1})
    with pytest.raises(ValueError, match="GPIO17 was not requested by mux"):
        lines.set_values({"GPIO17": 1})
    assert gpio.rec.named("set_values") == []


def test_get_values_reads_each_chip_once_as_ints(gpio):
    value = gpio.line.Value
    gpio.rec.will("get_values", [value.ACTIVE, value.INACTIVE], [value.ACTIVE])
    lines = LinuxGPIOLines(LineRequest({"GPIO2": 1}, {"GPIO17": None, "GPIO3": None}), consumer="probe")
    levels = lines.get_values(["GPIO3", "GPIO17", "GPIO2"])
    assert levels == {"GPIO3": 1, "GPIO17": 1, "GPIO2": 0}
    assert list(levels) == ["GPIO3", "GPIO17", "GPIO2"] and all(type(v) is int for v in levels.values())
    assert gpio.rec.named("get_values") == [("get_values", gpio.chip0, [3, 2]), ("get_values", gpio.chip1, [17])]


def test_wait_edge_returns_true_on_the_lines_event(gpio):
    gpio.rec.will("wait_edge_events", True)
    gpio.rec.will("read_edge_events", [gpio.fake.event(27)])
    lines = LinuxGPIOLines(LineRequest({}, {"GPIO27": FALLING}), consumer="adc")
    assert lines.wait_edge("GPIO27", 0.5) is True
    (_, path, timeout), = gpio.rec.named("wait_edge_events")
    assert path == gpio.chip1 and timedelta(0) < timeout <= timedelta(seconds=0.5)      # what is left of 0.5 s


def test_wait_edge_returns_false_on_timeout(gpio):
    gpio.rec.will("wait_edge_events", False)
    lines = LinuxGPIOLines(LineRequest({}, {"GPIO27": FALLING}), consumer="adc")
    assert lines.wait_edge("GPIO27", 0.01) is False
    assert len(gpio.rec.named("wait_edge_events")) == 1 and gpio.rec.named("read_edge_events") == []


def test_wait_edge_keeps_other_lines_events_for_their_own_wait(gpio):
    gpio.rec.will("wait_edge_events", True, True)
    gpio.rec.will("read_edge_events", [gpio.fake.event(17)], [gpio.fake.event(27)])
    lines = LinuxGPIOLines(LineRequest({}, {"GPIO17": RISING, "GPIO27": RISING}), consumer="adc")
    assert lines.wait_edge("GPIO27", 1.0) is True
    assert len(gpio.rec.named("wait_edge_events")) == 2
    assert lines.wait_edge("GPIO17", 1.0) is True
    assert len(gpio.rec.named("wait_edge_events")) == 2
    gpio.rec.will("wait_edge_events", False)
    assert lines.wait_edge("GPIO17", 0.0) is False


def test_drain_edges_empties_the_kernel_queue_without_waiting_and_keeps_other_lines_edges(gpio):
    gpio.rec.will("wait_edge_events", True, True, False)
    gpio.rec.will("read_edge_events", [gpio.fake.event(27), gpio.fake.event(17)], [gpio.fake.event(27)])
    lines = LinuxGPIOLines(LineRequest({}, {"GPIO17": RISING, "GPIO27": FALLING}), consumer="adc")
    assert lines.drain_edges("GPIO27") == 2
    assert [timeout for _, _, timeout in gpio.rec.named("wait_edge_events")] == [timedelta(0)] * 3
    assert lines.wait_edge("GPIO17", 1.0) is True
    gpio.rec.will("wait_edge_events", False)
    assert lines.wait_edge("GPIO27", 0.0) is False


def test_wait_edge_and_drain_edges_need_an_edge_input(gpio):
    lines = LinuxGPIOLines(LineRequest({"GPIO2": 0}, {"GPIO3": None}), consumer="adc")
    for name in ("GPIO2", "GPIO3"):
        with pytest.raises(ValueError, match=f"{name} of adc was not requested with edge detection"):
            lines.wait_edge(name, 0.1)
        with pytest.raises(ValueError, match=f"{name} of adc was not requested with edge detection"):
            lines.drain_edges(name)


def test_release_is_idempotent_and_final(gpio):
    lines = LinuxGPIOLines(LineRequest({"GPIO2": 0, "GPIO17": 0}, {}), consumer="mux")
    lines.release()
    lines.release()
    assert gpio.rec.named("release") == [("release", gpio.chip0), ("release", gpio.chip1)]
    with pytest.raises(BusError, match="after release"):
        lines.set_values({"GPIO2": 1})


def test_permission_denied_names_the_line_and_the_gpio_group(gpio):
    gpio.rec.will("request_lines", PermissionError(errno.EACCES, "Permission denied"))
    with pytest.raises(BusError, match=r"GPIO GPIO17 \(mux\): permission denied.*gpio group"):
        LinuxGPIOLines(LineRequest({"GPIO17": 0}, {}), consumer="mux")


def test_a_busy_line_is_bus_in_use_and_earlier_requests_are_released(gpio):
    gpio.rec.will("request_lines", None, OSError(errno.EBUSY, "Device or resource busy"))
    with pytest.raises(BusInUse, match="GPIO17"):
        LinuxGPIOLines(LineRequest({"GPIO2": 0, "GPIO17": 0}, {}), consumer="mux")
    assert gpio.rec.named("release") == [("release", gpio.chip0)]


@pytest.mark.parametrize("version", ["1.5.4", None])
def test_gpiod_before_2_1_is_backend_unavailable(gpio, version):
    gpio.fake.__version__ = version
    with pytest.raises(BackendUnavailable, match=r"gpiod 2\.1 or later.*found gpiod " + (version or "without")):
        LinuxGPIOLines(LineRequest({"GPIO17": 0}, {}), consumer="mux")
    assert gpio.rec.calls == []


def test_gpio_without_gpiod_is_backend_unavailable(monkeypatch):
    monkeypatch.setattr(linux_gpio, "gpiod", None)
    with pytest.raises(BackendUnavailable, match="pip install 'gpiod>=2.1'"):
        LinuxGPIOLines(LineRequest({"GPIO17": 0}, {}), consumer="mux")


# --- the board --------------------------------------------------------------------------------------------

def test_board_refuses_a_chip_select_twice(spi):
    board = LinuxBoard()
    device = board.spi(0, 0, mode=1, max_speed_hz=1_000_000, consumer="ads1256")
    with pytest.raises(BusInUse, match="spi0.0 is already in use by ads1256"):
        board.spi(0, 0, mode=1, max_speed_hz=1_000_000, consumer="ad5270")
    assert spi.named("open") == [("open", 0, 0)] and isinstance(device, LinuxSPIDevice)
    board.close()
    assert spi.named("close") == [("close",)]
    assert type(board.clock) is Clock


def test_board_passes_its_configured_gpio_chip(gpio):
    with LinuxBoard(gpio_chip=gpio.chip1) as board:
        board.gpio(LineRequest({"GPIO17": 0}, {}), consumer="mux")
        assert gpio.rec.named("Chip") == [("Chip", gpio.chip1)]
    assert gpio.rec.named("release") == [("release", gpio.chip1)]


# --- the real libraries on a machine without the hardware -------------------------------------------------

def test_the_parallel_boards_decoded_chip_select_runs_on_the_linux_buses(gpio, spi):
    """The AD7606 read-out through the 74HC154 decoder: gpiod sets the address (with CONVST low riding along),
    then one spidev frame; a conversion is CONVST high and BUSY's edge event."""
    from appliance.drivers.ad7606 import AD7606Array
    from appliance.drivers.decoder import ChipSelectDecoder

    value = gpio.line.Value
    gpio.fake.chips[gpio.chip1].update({"GPIO22": 22, "GPIO23": 23})
    names = dict(convst="GPIO17", busy="GPIO27", reset="GPIO22", range_line="GPIO23")
    lines = LinuxGPIOLines(AD7606Array.line_request(address_lines=("GPIO2", "GPIO3"), **names), consumer="adc")
    device = LinuxSPIDevice(1, 0, mode=AD7606Array.SPI_MODE, max_speed_hz=15_625_000)
    array = AD7606Array(lines, Clock(), ChipSelectDecoder(device, lines, ("GPIO2", "GPIO3")), n_chips=3, **names)
    gpio.rec.will("wait_edge_events", True)
    gpio.rec.will("read_edge_events", [gpio.fake.event(27)])
    spi.will("xfer2", [0x7F, 0xFF, 0xFF, 0xFE] + [0, 1] * 6)
    array.convert()
    assert array.read(2) == (32767, -2, 1, 1, 1, 1, 1, 1)
    assert gpio.rec.named("set_values") == [("set_values", gpio.chip1, {17: value.ACTIVE}),
                                            ("set_values", gpio.chip0, {2: value.INACTIVE, 3: value.ACTIVE}),
                                            ("set_values", gpio.chip1, {17: value.INACTIVE})]
    assert spi.named("xfer2") == [("xfer2", [0] * 16)] and ("set", "mode", 2) in spi.calls


def _absent(pattern):
    return pytest.mark.skipif(bool(glob.glob(pattern)), reason=f"{pattern} exists on this machine")


@_absent("/dev/spidev0.0")
def test_real_spidev_without_the_node_is_device_missing():
    pytest.importorskip("spidev")
    with pytest.raises(DeviceMissing, match=r"/dev/spidev0\.0") as caught:
        LinuxSPIDevice(0, 0, mode=0, max_speed_hz=1_000_000)
    assert isinstance(caught.value, FileNotFoundError)


@_absent("/dev/i2c-1")
def test_real_smbus2_without_the_adapter_is_device_missing():
    pytest.importorskip("smbus2")
    with pytest.raises(DeviceMissing, match="/dev/i2c-1") as caught:
        LinuxI2CBus(1)
    assert isinstance(caught.value, FileNotFoundError)


@_absent("/dev/gpiochip*")
def test_real_gpiod_without_a_chip_is_device_missing():
    pytest.importorskip("gpiod")
    with pytest.raises(DeviceMissing, match="GPIO17") as caught:
        LinuxGPIOLines(LineRequest({"GPIO17": 0}, {}), consumer="mux")
    assert isinstance(caught.value, FileNotFoundError)
    with pytest.raises(DeviceMissing, match="/dev/gpiochip0") as caught:
        LinuxGPIOLines(LineRequest({"GPIO17": 0}, {}), consumer="mux", chip_path="/dev/gpiochip0")
    assert isinstance(caught.value, FileNotFoundError)
