"""Opening the front end: the real board over Linux's buses or the emulated one, and the front end that its
profile's chain composes on it (AD5933, RMS converter, or parallel)."""

from __future__ import annotations

import logging
import warnings
from collections.abc import Callable, Mapping

from appliance.drivers.boards import System
from appliance.drivers.bus import Board
from appliance.drivers.emulated.analogue import SensorModel
from appliance.drivers.emulated.board import EmulatedBoard
from appliance.drivers.emulated.parallel_board import EmulatedParallelBoard
from appliance.drivers.frontend_ad5933 import AD5933FrontEnd
from appliance.drivers.frontend_parallel import ParallelFrontEnd
from appliance.drivers.frontend_rms import RMSFrontEnd
from appliance.drivers.profile import BoardProfile, board_profile
from appliance.errors import BackendUnavailable, ConfigError, DeviceMissing

log = logging.getLogger(__name__)

BACKENDS = ("linux", "emulated", "auto")


class EmulationFallbackWarning(UserWarning):
    """``backend = "auto"`` found no front end hardware and is running on the emulated board."""


def open_board(board: Mapping | None, *, sensor: Callable[[], SensorModel] | None = None,
               seed: int = 0) -> tuple[Board, BoardProfile]:
    """The board a ``[board]`` table asks for, with its profile.

    ``backend`` is ``"linux"`` (the real front end; missing hardware is an error
    naming the device), ``"emulated"`` (register-level emulators measuring
    ``sensor()``, a :class:`~appliance.drivers.emulated.analogue.SensorModel`), or
    ``"auto"``: the real one if it opens, else the emulated one with an
    :class:`EmulationFallbackWarning`, so an unattended fallback is never silent.
    ``seed`` fixes the emulated board's component errors and noise.
    """
    table = dict(board or {})
    backend = table.get("backend", "linux")
    if backend not in BACKENDS:
        raise ConfigError(f"[board] backend must be one of {BACKENDS}, got {backend!r}")
    profile = board_profile(table)
    if backend in ("linux", "auto"):
        try:
            return _linux_board(profile, table.get("gpio_chip")), profile
        except (BackendUnavailable, DeviceMissing) as exc:
            if backend == "linux":
                raise
            warnings.warn(f"no front end hardware ({exc}); running on the EMULATED board",
                          EmulationFallbackWarning, stacklevel=2)
            log.warning("no front end hardware (%s); running on the EMULATED board", exc)
    if sensor is None:
        raise ConfigError("the emulated board needs a sensor model (a layout to emulate)")
    return emulated_board(profile, sensor(), seed=seed), profile


def emulated_board(profile: BoardProfile, sensor: SensorModel, *, seed: int = 0, temperature_c: float = 24.0,
                   system: System | None = None) -> EmulatedBoard:
    """``profile``'s front end over emulated chips measuring ``sensor``: the parallel board when the profile's
    chain is ``parallel``, the serial one otherwise; ``seed`` fixes component errors and noise."""
    kind = EmulatedParallelBoard if profile.chain == "parallel" else EmulatedBoard
    return kind(profile, sensor, seed=seed, temperature_c=temperature_c, system=system)


def _linux_board(profile: BoardProfile, gpio_chip: str | None) -> Board:
    """A Linux board whose device files and lines have been found, so a missing one shows now.

    The profile is first held against the Pi it runs on (names, pins, SPI modes, enabled buses), so a
    mistake is named in one error instead of surfacing as a bare errno from one device. Lines are only
    looked up, not requested: requesting an output as an input, even briefly, could let the current
    source's enable float.
    """
    from appliance.drivers.board_check import check_profile, running_host
    from appliance.drivers.linux_board import LinuxBoard
    from appliance.drivers.linux_gpio import find_line_chips

    check_profile(profile, running_host())
    board = LinuxBoard(gpio_chip=gpio_chip)
    try:
        board.i2c(profile.i2c_bus)
        for role, address in profile.spi.items():
            board.spi(address.bus, address.chip_select, mode=0, max_speed_hz=address.max_speed_hz, consumer=role)
        if gpio_chip is None:
            find_line_chips(profile.gpio.values())
    finally:
        board.close()
    return LinuxBoard(gpio_chip=gpio_chip)


def open_front_end(board: Board, profile: BoardProfile):
    """The front end of ``profile`` on ``board``, its chips configured and the excitation off: a
    :class:`~appliance.drivers.frontend.FrontEnd`, or a parallel front end for the ``parallel`` chain."""
    if profile.chain == "parallel":
        return ParallelFrontEnd(board, profile)
    if profile.chain == "rms":
        return RMSFrontEnd(board, profile)
    return AD5933FrontEnd(board, profile)
