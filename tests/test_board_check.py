"""Board profiles held against the host boards and systems of drivers/boards.py: each mistake the issue
found on a real Pi, put back into a profile, is named; every built-in profile fits every board it claims."""

import dataclasses
import errno

import pytest

from appliance.cli import main
from appliance.drivers.adg7xx import ADG725
from appliance.drivers.board_check import check_profile, running_host
from appliance.drivers.boards import HOST_BOARDS, SYSTEMS
from appliance.drivers.bus import LineRequest
from appliance.drivers.backend import emulated_board
from appliance.drivers.profile import BUILTIN_PROFILES, board_profile
from appliance.errors import BoardMismatch, DeviceMissing, TransferFailed
from conftest import sensor_of


def mismatch(table: dict, board: str) -> str:
    with pytest.raises(BoardMismatch) as caught:
        check_profile(board_profile(table), HOST_BOARDS[board])
    return str(caught.value)


@pytest.mark.parametrize("name", BUILTIN_PROFILES)
def test_every_builtin_profile_fits_every_board_it_claims_on_the_image(name):
    profile = board_profile({"profile": name})
    assert profile.boards, f"{name} claims no board"
    assert profile.system.startswith("appliance-image"), f"{name} does not run on the appliance's image"
    for board in profile.boards:
        check_profile(profile, HOST_BOARDS[board])


def test_a_multiplexer_in_spi_mode_1_on_the_auxiliary_spi1_is_refused(monkeypatch):
    monkeypatch.setattr(ADG725, "SPI_MODE", 1)
    message = mismatch({"profile": "reference"}, "pi4b")
    assert "/dev/spidev1.0 (measure_mux): the ADG725 is opened in SPI mode 1" in message
    assert "spi-bcm2835aux" in message and "only modes [0, 2]" in message and "EINVAL" in message
    assert "spidev0.1" not in message                       # SPI0 takes every mode


def test_gpio4_by_the_name_another_kernel_gives_it_is_refused_with_its_real_name():
    message = mismatch({"profile": "reference", "gpio": {"adc_ready": "GPIO4"}}, "pi4b")
    assert "adc_ready = 'GPIO4': pi4b has no line of that name under the mainline kernel" in message
    assert "GPIO 4 is named 'GPIO_GCLK' there" in message
    pi_os = {"profile": "reference", "system": "raspberry-pi-os-spi1-1cs", "gpio": {"adc_ready": "GPIO4"}}
    check_profile(board_profile(pi_os), HOST_BOARDS["pi4b"])
    assert "pi3b has no line of that name under the raspberrypi kernel" in mismatch(pi_os, "pi3b")


def test_a_line_used_as_a_chip_select_and_the_led_is_refused():
    message = mismatch({"profile": "reference-32", "gpio": {"status_led": "GPIO16"}}, "pi4b")
    assert "status_led = 'GPIO16': GPIO 16 is already SPI1 CE2 (meas_neg_mux)" in message


def test_a_pin_an_enabled_bus_claims_is_refused():
    message = mismatch({"profile": "reference", "gpio": {"buzzer": "SDA1"}}, "pi4b")
    assert "buzzer = 'SDA1': GPIO 2 is I2C1 SDA, which appliance-image enables" in message
    message = mismatch({"profile": "ad5933", "gpio": {"buzzer": "GPIO9"}}, "pi3b")
    assert "buzzer = 'GPIO9': pi3b has no line of that name" in message     # SPI_MISO under that kernel
    message = mismatch({"profile": "ad5933", "gpio": {"buzzer": "SPI_MISO"}}, "pi3b")
    assert "GPIO 9 is SPI0 MISO" in message


def test_a_bus_the_image_does_not_enable_is_refused():
    message = mismatch({"profile": "reference-32", "system": "appliance-image"}, "pi4b")
    assert "/dev/spidev1.1 (meas_pos_mux): appliance-image enables only 1 chip select(s) on SPI1" in message
    assert "/dev/spidev1.2 (meas_neg_mux)" in message       # every problem at once, not the first only
    message = mismatch({"profile": "parallel", "system": "appliance-image-spi1-3cs"}, "pi4b")
    assert "adc_convst = 'GPIO17': GPIO 17 is SPI1 CE1, which appliance-image-spi1-3cs enables" in message


def test_the_pi5_image_lacks_spi_and_says_why():
    message = mismatch({"profile": "reference", "system": "appliance-image-pi5"}, "pi5")
    assert "/dev/spidev0.0 (dds): appliance-image-pi5 does not enable SPI0" in message
    assert "/dev/spidev1.0 (measure_mux): appliance-image-pi5 does not enable SPI1" in message
    assert "CONFIG_SPI_DESIGNWARE is not set" in message
    assert "I2C1 ([board.i2c] bus): appliance-image-pi5 does not enable it (it enables I2C none)" in message
    message = mismatch({"profile": "reference"}, "pi5")
    assert "appliance-image is built for pi3b, pi3b-plus, pi4b, not pi5" in message


def test_an_i2c_bus_slower_than_the_profile_s_timing_is_refused():
    profile = board_profile({"profile": "ad5933"})
    default_clock = dataclasses.replace(SYSTEMS["appliance-image"], i2c_clock_hz={1: 100_000})
    with pytest.raises(BoardMismatch, match=r"I2C1 runs at 100 kHz under appliance-image, but the profile's timing "
                                            r"needs 400 kHz \(\[board.timing\] i2c_clock_hz\)"):
        check_profile(profile, HOST_BOARDS["pi4b"], default_clock)
    check_profile(board_profile({"profile": "ad5933", "timing": {"i2c_clock_hz": 100_000}}), HOST_BOARDS["pi4b"],
                  default_clock)


def test_the_emulated_i2c_bus_runs_at_the_system_s_clock_not_the_profile_s():
    """The AD5933's set-pointer command (address, 0xB0, register: 27 clocks) on the wire at the system's clock."""
    profile = board_profile({"profile": "ad5933", "timing": {"i2c_clock_hz": 1_000_000}})
    spent = {}
    for clock in (400_000, 100_000):
        system = dataclasses.replace(SYSTEMS["appliance-image"], i2c_clock_hz={1: clock})
        board = emulated_board(profile, sensor_of("grid-4x4"), system=system)
        assert board.timing.i2c_clock_hz == clock
        bus = board.i2c(1)
        start = board.clock.monotonic()
        bus.write(profile.i2c["impedance"], bytes([0xB0, 0x8F]))
        spent[clock] = board.clock.monotonic() - start
    wire = {clock: spent[clock] - profile.timing.call_overhead_s for clock in spent}
    assert wire[100_000] == pytest.approx(4 * wire[400_000])
    assert wire[400_000] == pytest.approx(3 * 9 / 400_000)


def test_the_serial_console_of_the_image_keeps_its_pins():
    message = mismatch({"profile": "reference", "system": "appliance-image", "gpio": {"buzzer": "TXD1"}}, "pi4b")
    assert "buzzer = 'TXD1': GPIO 14 is UART1 TXD (the serial console, ttyS1)" in message


def test_unverified_names_place_only_numbered_lines():
    assert HOST_BOARDS["pi5"].names("mainline") is None
    any_board = dataclasses.replace(SYSTEMS["appliance-image"], boards=())
    check_profile(board_profile({"profile": "ad5933", "spi": {
        "measure_mux": {"bus": 0, "chip_select": 0, "max_speed_hz": 10_000_000}}}), HOST_BOARDS["pi5"], any_board)
    with pytest.raises(BoardMismatch) as caught:
        check_profile(board_profile({"profile": "reference", "gpio": {"buzzer": "GPIO_GCLK"}}), HOST_BOARDS["pi5"],
                      any_board)
    message = str(caught.value)
    assert "line names of pi5 under the mainline kernel are not verified" in message


def test_the_running_board_is_read_from_the_device_tree(tmp_path):
    compatible = tmp_path / "compatible"
    compatible.write_bytes(b"raspberrypi,4-model-b\0brcm,bcm2711\0")
    assert running_host(compatible).name == "pi4b"
    compatible.write_bytes(b"raspberrypi,400\0brcm,bcm2711\0")
    assert running_host(compatible).name == "generic"
    assert running_host(tmp_path / "absent").name == "generic"


def test_the_linux_board_refuses_a_profile_that_does_not_fit_before_opening_anything(monkeypatch):
    from appliance.drivers.backend import open_board

    monkeypatch.setattr("appliance.drivers.board_check.running_host", lambda: HOST_BOARDS["pi4b"])
    with pytest.raises(BoardMismatch, match="GPIO 16 is already SPI1 CE2"):
        open_board({"backend": "linux", "profile": "reference-32", "gpio": {"status_led": "GPIO16"}})


def test_the_emulated_spi1_refuses_cpha_1_as_the_kernel_does():
    board = emulated_board(board_profile({"profile": "reference"}), sensor_of("grid-4x4"))
    with pytest.raises(TransferFailed, match="spidev1.0: Invalid argument: mode 1") as caught:
        board.spi(1, 0, mode=1, max_speed_hz=1_000_000, consumer="measure_mux")
    assert caught.value.errno == errno.EINVAL
    board.spi(1, 0, mode=2, max_speed_hz=1_000_000, consumer="measure_mux").close()


def test_the_emulated_lines_carry_the_names_of_the_systems_kernel():
    board = emulated_board(board_profile({"profile": "ad5933", "system": "appliance-image"}), sensor_of("grid-4x4"))
    assert "GPIO_GCLK" in board.bank.names and "GPIO4" not in board.bank.names
    with pytest.raises(DeviceMissing, match="GPIO4"):
        board.gpio(LineRequest(outputs={"GPIO4": 0}, inputs={}), consumer="test")
    assert SYSTEMS["appliance-image"].kernel == "mainline"


def test_selftest_check_passes_and_fails_with_status_2(tmp_path, capsys):
    assert main(["selftest", "--check", "--profile", "reference-32"]) == 0
    out = capsys.readouterr().out
    assert "profile reference-32 fits pi4b (Raspberry Pi 4 Model B) running appliance-image-spi1-3cs" in out
    config = tmp_path / "appliance.toml"
    config.write_text('[board]\nprofile = "reference-32"\n[board.gpio]\nstatus_led = "GPIO16"\n')
    assert main(["selftest", "--check", "--config", str(config), "--board", "pi3b"]) == 2
    assert "GPIO 16 is already SPI1 CE2 (meas_neg_mux)" in capsys.readouterr().err
    assert main(["selftest", "--board", "pi4b", "--emulated"]) == 2
