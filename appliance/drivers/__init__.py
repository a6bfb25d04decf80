"""The front end's drivers: bus interfaces, Linux buses, one module per chip, the scan engine.

Data flows one way: a :class:`~appliance.drivers.bus.Board` hands out buses, chip
drivers take them by injection, the front end composes the chips, and the scan
engine turns a protocol into a frame of readings with quality flags.
:func:`open_board` is the one place that chooses between the real board and the
emulated one.
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING

from appliance.drivers.bus import Board
from appliance.drivers.profile import BoardProfile, board_profile
from appliance.errors import BackendUnavailable, ConfigError, DeviceMissing

if TYPE_CHECKING:
    from appliance.drivers.emulated.analogue import SensorModel

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
    from appliance.drivers.emulated.board import EmulatedBoard

    return EmulatedBoard(profile, sensor(), seed=seed), profile


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
