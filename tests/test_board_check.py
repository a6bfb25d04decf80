"""Board profiles held against the host boards and systems of drivers/boards.py: each mistake the issue
found on a real Pi, put back into a profile, is named; every built-in profile fits every board it claims."""

import errno

import pytest

from appliance.cli import main
from appliance.drivers.adg7xx import ADG725
from appliance.drivers.board_check import check_profile, running_host
from appliance.drivers.boards import HOST_BOARDS, SYSTEMS
from appliance.drivers.bus import LineRequest
from appliance.drivers.emulated.board import EmulatedBoard
from appliance.drivers.profile import BUILTIN_PROFILES, board_profile
from appliance.errors import BoardMismatch, DeviceMissing, TransferFailed
from conftest import sensor_of


def mismatch(table: dict, board: str) -> str:
    with pytest.raises(BoardMismatch) as caught:
        check_profile(board_profile(table), HOST_BOARDS[board])
    return str(caught.value)


@pytest.mark.parametrize("name", BUILTIN_PROFILES)
def test_every_builtin_profile_fits_every_board_it_claims(name):
    profile = board_profile({"profile": name})
    assert profile.boards, f"{name} claims no board"
    for board in profile.boards:
        check_profile(profile, HOST_BOARDS[board])


def test_a_multiplexer_in_spi_mode_1_on_the_auxiliary_spi1_is_refused(monkeypatch):
    monkeypatch.setattr(ADG725, "SPI_MODE", 1)
    message = mismatch({"profile": "reference"}, "pi4b")
    assert "/dev/spidev1.0 (measure_mux): the ADG725 is opened in SPI mode 1" in message
    assert "spi-bcm2835aux" in message and "only modes [0, 2]" in message and "EINVAL" in message
    assert "spidev0.1" not in message                       # SPI0 takes every mode


def test_gpio4_by_the_name_another_kernel_gives_it_is_refused_with_its_real_name():
    message = mismatch({"profile": "reference", "gpio": {"adc_ready": "GPIO4"}}, "pi3b")
    assert "adc_ready = 'GPIO4': pi3b has no line of that name under the raspberrypi kernel" in message
    assert "GPIO 4 is named 'GPIO_GCLK' there" in message
    check_profile(board_profile({"profile": "reference", "gpio": {"adc_ready": "GPIO4"}}), HOST_BOARDS["pi4b"])


def test_a_line_used_as_a_chip_select_and_the_led_is_refused():
    message = mismatch({"profile": "reference-32", "gpio": {"status_led": "GPIO16"}}, "pi4b")
    assert "status_led = 'GPIO16': GPIO 16 is already SPI1 CE2 (meas_neg_mux)" in message


def test_a_pin_an_enabled_bus_claims_is_refused():
    message = mismatch({"profile": "reference", "gpio": {"buzzer": "GPIO2"}}, "pi4b")
    assert "buzzer = 'GPIO2': GPIO 2 is I2C1 SDA, which raspberry-pi-os-spi1-1cs enables" in message
    message = mismatch({"profile": "ad5933", "gpio": {"buzzer": "GPIO9"}}, "pi3b")
    assert "buzzer = 'GPIO9': pi3b has no line of that name" in message     # SPI_MISO under that kernel
    message = mismatch({"profile": "ad5933", "gpio": {"buzzer": "SPI_MISO"}}, "pi3b")
    assert "GPIO 9 is SPI0 MISO" in message


def test_a_bus_the_image_does_not_enable_is_refused():
    message = mismatch({"profile": "reference", "system": "appliance-image"}, "pi4b")
    assert "/dev/spidev1.0 (measure_mux): appliance-image does not enable SPI1" in message
    message = mismatch({"profile": "reference-32", "system": "raspberry-pi-os-spi1-1cs"}, "pi4b")
    assert "/dev/spidev1.1 (meas_pos_mux): raspberry-pi-os-spi1-1cs enables only 1 chip select(s) on SPI1" in message
    assert "/dev/spidev1.2 (meas_neg_mux)" in message       # every problem at once, not the first only


def test_the_serial_console_of_the_image_keeps_its_pins():
    message = mismatch({"profile": "reference", "system": "appliance-image", "gpio": {"buzzer": "TXD1"}}, "pi4b")
    assert "buzzer = 'TXD1': GPIO 14 is UART1 TXD (the serial console, ttyS1)" in message


def test_unverified_names_place_only_numbered_lines():
    assert HOST_BOARDS["pi5"].names("mainline") is None
    check_profile(board_profile({"profile": "ad5933", "system": "appliance-image", "spi": {
        "measure_mux": {"bus": 0, "chip_select": 0, "max_speed_hz": 10_000_000}}}), HOST_BOARDS["pi5"])
    message = mismatch({"profile": "reference", "system": "appliance-image", "gpio": {"buzzer": "GPIO_GCLK"}}, "pi5")
    assert "line names of pi5 under the mainline kernel are not verified" in message


def test_the_running_board_is_read_from_the_device_tree(tmp_path):
    compatible = tmp_path / "compatible"
    compatible.write_bytes(b"raspberrypi,4-model-b\0brcm,bcm2711\0")
    assert running_host(compatible).name == "pi4b"
    compatible.write_bytes(b"raspberrypi,400\0brcm,bcm2711\0")
    assert running_host(compatible).name == "generic"
    assert running_host(tmp_path / "absent").name == "generic"


def test_the_linux_board_refuses_a_profile_that_does_not_fit_before_opening_anything(monkeypatch):
    from appliance.drivers import open_board

    monkeypatch.setattr("appliance.drivers.board_check.running_host", lambda: HOST_BOARDS["pi4b"])
    with pytest.raises(BoardMismatch, match="GPIO 16 is already SPI1 CE2"):
        open_board({"backend": "linux", "profile": "reference-32", "gpio": {"status_led": "GPIO16"}})


def test_the_emulated_spi1_refuses_cpha_1_as_the_kernel_does():
    board = EmulatedBoard(board_profile({"profile": "reference"}), sensor_of("grid-4x4"))
    with pytest.raises(TransferFailed, match="spidev1.0: Invalid argument: mode 1") as caught:
        board.spi(1, 0, mode=1, max_speed_hz=1_000_000, consumer="measure_mux")
    assert caught.value.errno == errno.EINVAL
    board.spi(1, 0, mode=2, max_speed_hz=1_000_000, consumer="measure_mux").close()


def test_the_emulated_lines_carry_the_names_of_the_systems_kernel():
    board = EmulatedBoard(board_profile({"profile": "ad5933", "system": "appliance-image"}), sensor_of("grid-4x4"))
    assert "GPIO_GCLK" in board.bank.names and "GPIO4" not in board.bank.names
    with pytest.raises(DeviceMissing, match="GPIO4"):
        board.gpio(LineRequest(outputs={"GPIO4": 0}, inputs={}), consumer="test")
    assert SYSTEMS["appliance-image"].kernel == "mainline"


def test_selftest_check_passes_and_fails_with_status_2(tmp_path, capsys):
    assert main(["selftest", "--check", "--profile", "reference-32"]) == 0
    out = capsys.readouterr().out
    assert "profile reference-32 fits pi4b (Raspberry Pi 4 Model B) running raspberry-pi-os-spi1-3cs" in out
    config = tmp_path / "appliance.toml"
    config.write_text('[board]\nprofile = "reference-32"\n[board.gpio]\nstatus_led = "GPIO16"\n')
    assert main(["selftest", "--check", "--config", str(config), "--board", "pi3b"]) == 2
    assert "GPIO 16 is already SPI1 CE2 (meas_neg_mux)" in capsys.readouterr().err
    assert main(["selftest", "--board", "pi4b", "--emulated"]) == 2
