"""The Linux board on a real kernel, with the real gpiod, smbus2 and spidev: run as root inside the test VM.

``tests/test_kernel_buses.py`` boots the VM (``vm.py``) and runs this module there; each of its tests is
reported back as one host test. It refuses to run anywhere else (it would reconfigure the machine's GPIO).

* GPIO: gpio-sim, configured here through configfs, gives two chips: a decoy, then a Raspberry Pi 4B's
  header lines named as ``boards.py`` has them for the appliance image's kernel. The drivers find lines by
  name and request them through the GPIO character device as on a Pi; the tests play the wiring through
  each simulated line's ``pull`` and read what the drivers drive from its ``value`` (sysfs).
* I2C: i2c-stub answers at the reference profile's ADC and thermometer addresses (the VM loads it with
  them) and keeps one 16-bit word per register. It never converts: a test writes the conversion register
  as the chip would, and makes ALERT/RDY's edge through gpio-sim. An address nobody answers at gives
  ENODEV from i2c-stub, where a Pi's controller gives EREMOTEIO.
* SPI: the kernel has no SPI controller that simulates a chip (Debian does not build ``spi-loopback-test``,
  which needs a wired controller anyway), so only a missing device node is checked.
"""

import errno
import os
import re
from dataclasses import dataclass, replace
from pathlib import Path

import pytest
from smbus2 import SMBus

from appliance.drivers.ads1115 import ADS1115, CONFIG, CONVERSION, HI_THRESH, LO_THRESH, OS_START, config_word
from appliance.drivers.board_check import check_profile
from appliance.drivers.boards import DEFAULT_SYSTEM, HOST_BOARDS, SYSTEMS
from appliance.drivers.bus import FALLING, PULL_UP, LineRequest
from appliance.drivers.linux_board import LinuxBoard
from appliance.drivers.linux_gpio import find_line_chips, gpiochip_paths
from appliance.drivers.mcp9808 import MCP9808
from appliance.drivers.profile import board_profile
from appliance.errors import BoardMismatch, BusInUse, ChipNotResponding, DeviceMissing, TransferFailed

GUEST_MARK = "APPLIANCE_KERNEL_GUEST"
"""Set by the VM's command line for this module; nowhere else does it reconfigure GPIO."""
CONFIGFS = Path("/sys/kernel/config/gpio-sim")
PI, SYSTEM = HOST_BOARDS["pi4b"], SYSTEMS[DEFAULT_SYSTEM]
PI_LINE_NAMES = PI.names(SYSTEM.kernel)
PROFILE = board_profile({"profile": "reference"})
ADC, THERMOMETER = PROFILE.i2c["adc"], PROFILE.i2c["thermometer"]

pytestmark = pytest.mark.skipif(os.environ.get(GUEST_MARK) != "1",
                                reason="runs inside the test VM only (tests/test_kernel_buses.py boots it)")


@dataclass(frozen=True)
class SimulatedPi:
    """The gpio-sim device: the decoy chip's and the header chip's device paths, and the header's sysfs folder."""

    decoy: str
    header: str
    sysfs: Path

    def pull(self, name: str, level: int) -> None:
        """What the wiring does to an input: pull the line ``name`` high (1) or low (0)."""
        (self.sysfs / f"sim_gpio{PI_LINE_NAMES.index(name)}" / "pull").write_text("pull-up" if level else "pull-down")

    def level(self, name: str) -> int:
        """The level of the line ``name`` as the pin has it (what an output drives)."""
        return int((self.sysfs / f"sim_gpio{PI_LINE_NAMES.index(name)}" / "value").read_text())


def _bank(device: Path, bank: str, names) -> Path:
    folder = device / bank
    folder.mkdir()
    (folder / "num_lines").write_text(str(len(names)))
    for offset, name in enumerate(names):
        (folder / f"line{offset}").mkdir()
        (folder / f"line{offset}" / "name").write_text(name)
    return folder


@pytest.fixture(scope="module")
def pi() -> SimulatedPi:
    device = CONFIGFS / "appliance"
    device.mkdir()
    decoy = _bank(device, "bank0-decoy", [f"DECOY{n}" for n in range(8)])
    header = _bank(device, "bank1-header", PI_LINE_NAMES)
    (device / "live").write_text("1")
    dev_name = (device / "dev_name").read_text().strip()
    header_chip = (header / "chip_name").read_text().strip()
    return SimulatedPi(f"/dev/{(decoy / 'chip_name').read_text().strip()}", f"/dev/{header_chip}",
                       Path("/sys/devices/platform") / dev_name / header_chip)


@pytest.fixture(scope="module")
def i2c_bus() -> int:
    """The number of i2c-stub's adapter (/dev/i2c-N)."""
    for folder in Path("/sys/bus/i2c/devices").glob("i2c-*"):
        if (folder / "name").read_text().strip() == "SMBus stub driver":
            return int(folder.name.removeprefix("i2c-"))
    raise AssertionError("i2c-stub's adapter is missing")


def preload(bus: int, address: int, register: int, word: int) -> None:
    """Put ``word`` in a register of i2c-stub's chip, most significant byte first on the wire as the chip sends it.

    Written with smbus2 directly, apart from the code under test: SMBus words travel low byte first.
    """
    with SMBus(bus) as smbus:
        smbus.write_word_data(address, register, int.from_bytes(word.to_bytes(2, "big"), "little"))


def stored(bus: int, address: int, register: int) -> int:
    with SMBus(bus) as smbus:
        return int.from_bytes(smbus.read_word_data(address, register).to_bytes(2, "little"), "big")


@pytest.fixture
def board():
    with LinuxBoard() as board:
        yield board


# --- GPIO -------------------------------------------------------------------------------------------------

def test_lines_are_found_by_the_pis_names_on_whichever_chip_has_them(pi):
    assert gpiochip_paths() == sorted([pi.decoy, pi.header], key=lambda path: int(path.removeprefix("/dev/gpiochip")))
    found = find_line_chips(PROFILE.gpio.values())
    assert found == dict.fromkeys(PROFILE.gpio.values(), pi.header)
    assert find_line_chips(["SDA1", "DECOY3"]) == {"SDA1": pi.header, "DECOY3": pi.decoy}


def test_outputs_drive_the_pins_together_and_read_back(pi, board):
    a0, a1, wr = PROFILE.gpio["gain_a0"], PROFILE.gpio["gain_a1"], PROFILE.gpio["gain_wr"]
    lines = board.gpio(LineRequest(outputs={a0: 0, a1: 1, wr: 1}, inputs={}), consumer="pga")
    assert [pi.level(name) for name in (a0, a1, wr)] == [0, 1, 1]
    lines.set_values({a0: 1, a1: 0, wr: 0})
    assert [pi.level(name) for name in (a0, a1, wr)] == [1, 0, 0]
    assert lines.get_values() == {a0: 1, a1: 0, wr: 0}


def test_inputs_read_what_the_wiring_pulls(pi, board):
    sign = PROFILE.gpio["phase_sign"]
    lines = board.gpio(LineRequest(outputs={}, inputs={sign: None}), consumer="demodulator")
    pi.pull(sign, 1)
    assert lines.get_values() == {sign: 1}
    pi.pull(sign, 0)
    assert lines.get_values([sign]) == {sign: 0}


def test_edges_are_queued_counted_and_drained(pi, board):
    ready = PROFILE.gpio["adc_ready"]
    pi.pull(ready, 1)
    lines = board.gpio(LineRequest(outputs={}, inputs={ready: FALLING}, bias={ready: PULL_UP}), consumer="adc")
    assert not lines.wait_edge(ready, 0.05)
    for _ in range(3):
        pi.pull(ready, 0)
        pi.pull(ready, 1)           # rising edges are not asked for, so not counted
    assert lines.wait_edge(ready, 1.0)
    assert lines.drain_edges(ready) == 2
    assert not lines.wait_edge(ready, 0.05)


def test_a_line_held_by_another_program_is_bus_in_use(pi, board):
    led = PROFILE.gpio["status_led"]
    board.gpio(LineRequest(outputs={led: 0}, inputs={}), consumer="status LED")
    with LinuxBoard() as other, pytest.raises(BusInUse, match=f"GPIO {led} \\(second LED\\): busy"):
        other.gpio(LineRequest(outputs={led: 1}, inputs={}), consumer="second LED")
    assert pi.level(led) == 0


def test_a_line_the_pi_names_otherwise_is_refused_by_the_board_check_and_missing_on_the_kernel(pi):
    # The appliance image's mainline kernel calls GPIO 4 "GPIO_GCLK": the board check says so before anything
    # opens...
    wrong = replace(PROFILE, gpio={**PROFILE.gpio, "adc_ready": "GPIO4"})
    with pytest.raises(BoardMismatch, match="adc_ready = 'GPIO4': pi4b has no line of that name under the "
                                            "mainline kernel; GPIO 4 is named 'GPIO_GCLK' there"):
        check_profile(wrong, PI, SYSTEM)
    # ...and the kernel, searched, agrees.
    searched = ", ".join(gpiochip_paths())
    with pytest.raises(DeviceMissing, match=re.escape(f"GPIO line GPIO4 is on none of the GPIO chips searched "
                                                      f"({searched})")):
        find_line_chips(["GPIO4"])
    assert find_line_chips(["GPIO_GCLK"]) == {"GPIO_GCLK": pi.header}


# --- I2C --------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("code", [12345, -12345, 32767, -32768])
def test_ads1115_reads_its_conversion_at_the_ready_edge(pi, i2c_bus, board, code):
    ready = PROFILE.gpio["adc_ready"]
    lines = board.gpio(LineRequest(outputs={}, inputs={ready: FALLING}, bias={ready: PULL_UP}), consumer="adc")
    pi.pull(ready, 0)                   # ALERT/RDY idles low in single-shot mode
    adc = ADS1115(board.i2c(i2c_bus), board.clock, address=ADC, ready=lines, ready_line=ready)
    assert (stored(i2c_bus, ADC, HI_THRESH), stored(i2c_bus, ADC, LO_THRESH)) == (0x8000, 0x0000)
    adc.start("AIN0", 4.096, 860)
    assert stored(i2c_bus, ADC, CONFIG) == OS_START | config_word("AIN0", 4.096, 860, ready_pin=True)
    pi.pull(ready, 1)                   # converting
    preload(i2c_bus, ADC, CONVERSION, code & 0xFFFF)
    pi.pull(ready, 0)                   # done: the falling edge
    assert adc.read_code(860) == code


def test_ads1115_self_test_reads_its_config_back_and_its_edge_is_not_taken_for_a_conversion(pi, i2c_bus, board):
    ready = PROFILE.gpio["adc_ready"]
    pi.pull(ready, 1)
    lines = board.gpio(LineRequest(outputs={}, inputs={ready: FALLING}, bias={ready: PULL_UP}), consumer="adc")
    adc = ADS1115(board.i2c(i2c_bus), board.clock, address=ADC, ready=lines, ready_line=ready)
    adc.check()
    pi.pull(ready, 0)                   # the idle chip pulls ALERT/RDY low at the config write
    preload(i2c_bus, ADC, CONVERSION, 0x1234)
    adc.start("AIN0", 4.096, 860)
    with pytest.raises(ChipNotResponding, match=f"ADS1115\\(0x48\\): ALERT/RDY on {ready} did not signal"):
        adc.read_code(860)


def test_mcp9808_identity_and_temperature(i2c_bus, board):
    preload(i2c_bus, THERMOMETER, 0x06, 0x0054)
    preload(i2c_bus, THERMOMETER, 0x07, 0x0401)
    thermometer = MCP9808(board.i2c(i2c_bus), address=THERMOMETER)
    assert thermometer.check_identity() == 1
    preload(i2c_bus, THERMOMETER, 0x05, 0xC179)     # alert flags set, +23.5625 degC
    assert thermometer.temperature_c() == 23.5625
    preload(i2c_bus, THERMOMETER, 0x05, 0x1FAC)
    assert thermometer.temperature_c() == -5.25


def test_a_chip_that_is_not_there_is_a_transfer_failure_naming_bus_and_address(i2c_bus, board):
    with pytest.raises(TransferFailed, match=f"I2C bus {i2c_bus} address 0x19: No such device") as caught:
        MCP9808(board.i2c(i2c_bus), address=0x19).temperature_c()
    assert caught.value.errno == errno.ENODEV


def test_a_missing_adapter_is_device_missing_with_a_hint(board):
    with pytest.raises(DeviceMissing, match="/dev/i2c-7 does not exist: is I2C enabled"):
        board.i2c(7)


# --- SPI --------------------------------------------------------------------------------------------------

def test_a_missing_spi_node_is_device_missing_with_a_hint(board):
    with pytest.raises(DeviceMissing, match=r"/dev/spidev0\.0 does not exist: is SPI enabled"):
        board.spi(0, 0, mode=1, max_speed_hz=1_000_000, consumer="adc")

