"""GPIO lines by header name ("GPIO17") on Linux through libgpiod v2 (the ``gpiod`` package, 2.1 or later).

Lines are found by name, never through a hard-coded chip: which
``/dev/gpiochipN`` carries the header differs between Pi models and kernels (a
Pi 5's ``pinctrl-rp1`` moved from gpiochip4 to gpiochip0, and later kernels
number it 10 and up). A chip path from the configuration skips the search.
Lines spread over several chips get one request per chip; the outputs of one
chip change together in one ioctl, those of different chips one chip after another.
"""

from __future__ import annotations

import errno
import glob
import os
import re
import time
from collections.abc import Iterable, Mapping, Sequence
from datetime import timedelta

from appliance.drivers.bus import FALLING, PULL_DOWN, PULL_UP, RISING, GPIOLines, LineRequest, os_error_to_bus_error
from appliance.errors import BackendUnavailable, BusError, DeviceMissing

try:
    import gpiod
except ImportError:
    gpiod = None    # type: ignore[assignment]  # absent off Linux; _require_gpiod says so before any use

MIN_VERSION = (2, 1)


def _require_gpiod() -> None:
    """Refuse a missing gpiod, and the unrelated PyPI gpiod 1.x or the libgpiod v1 bindings (Debian bookworm)."""
    if gpiod is None:
        raise BackendUnavailable("GPIO needs libgpiod's Python bindings: pip install 'gpiod>=2.1'")
    found = getattr(gpiod, "__version__", None)
    match = re.match(r"(\d+)\.(\d+)", str(found))
    if match is None or (int(match[1]), int(match[2])) < MIN_VERSION:
        raise BackendUnavailable(f"GPIO needs gpiod 2.1 or later (the libgpiod v2 API), found gpiod "
                                 f"{found or 'without a version (the libgpiod v1 bindings?)'}: "
                                 "pip install 'gpiod>=2.1' (Debian bookworm's python3-libgpiod is the v1 API)")


def _gpio_error(where: str, exc: OSError) -> Exception:
    if exc.errno == errno.EACCES:
        return BusError(f"{where}: permission denied; add the user to the gpio group "
                        "(sudo usermod -aG gpio USER) and log in again")
    return os_error_to_bus_error(where, exc)


def gpiochip_paths(directory: str = "/dev") -> list[str]:
    """The GPIO chip devices in ``directory`` in chip-number order (gpiochip2 before gpiochip10)."""
    _require_gpiod()
    paths = [path for path in glob.glob(os.path.join(directory, "gpiochip*")) if gpiod.is_gpiochip_device(path)]
    return sorted(paths, key=lambda path: (_chip_number(path), path))


def _chip_number(path: str) -> int:
    number = re.search(r"\d+$", path)
    return int(number[0]) if number else -1


def _locate(names: Sequence[str], chip_paths: Iterable[str] | None) -> dict[str, tuple[str, int]]:
    """``{name: (chip path, offset)}``, each line on the first chip that knows its name."""
    _require_gpiod()
    paths = gpiochip_paths() if chip_paths is None else list(chip_paths)
    found: dict[str, tuple[str, int]] = {}
    for path in paths:
        wanted = [name for name in names if name not in found]
        if not wanted:
            break
        try:
            chip = gpiod.Chip(path)
        except OSError as exc:
            raise _gpio_error(f"GPIO chip {path}", exc) from exc
        with chip:
            for name in wanted:
                try:
                    found[name] = (path, chip.line_offset_from_id(name))
                except OSError:
                    continue
    for name in names:
        if name not in found:
            if not paths:
                raise DeviceMissing(f"GPIO line {name}: no GPIO chip exists (no /dev/gpiochip* device; "
                                    "the GPIO controller's driver is missing or this is not a Pi)")
            raise DeviceMissing(f"GPIO line {name} is on none of the GPIO chips searched ({', '.join(paths)})")
    return found


def find_line_chips(names: Iterable[str], chip_paths: Iterable[str] | None = None) -> dict[str, str]:
    """``{line name: chip path}``, searching ``chip_paths`` (default: every /dev/gpiochip*) in order.

    Raises :class:`~appliance.errors.DeviceMissing` naming a line no chip has.
    """
    return {name: path for name, (path, _) in _locate(list(names), chip_paths).items()}


class LinuxGPIOLines(GPIOLines):
    """The lines of ``request``, held for ``consumer`` (the name ``gpioinfo`` shows) until released.

    ``chip_path`` restricts the search to one chip (from the configuration).
    """

    def __init__(self, request: LineRequest, *, consumer: str, chip_path: str | None = None):
        _require_gpiod()
        self.names, self.consumer = request.names, consumer
        self._outputs, self._edges = set(request.outputs), dict(request.inputs)
        self._where = _locate(self.names, None if chip_path is None else [chip_path])
        self._line_at = {where: name for name, where in self._where.items()}
        self._pending = dict.fromkeys(self._edges, 0)
        self._requests: dict[str, gpiod.LineRequest] = {}
        self._released = False
        try:
            for path, lines in self._by_chip(self.names).items():
                config = {offset: self._settings(name, request) for name, offset in lines}
                self._requests[path] = self._call([name for name, _ in lines], gpiod.request_lines,
                                                  path, config, consumer=consumer)
        except BusError:
            self.release()
            raise

    def _settings(self, name: str, request: LineRequest):
        """An output at its first value, or an input watching the edge it was requested with, biased as asked."""
        line = gpiod.line
        if name in self._outputs:
            return gpiod.LineSettings(direction=line.Direction.OUTPUT, output_value=_value(request.outputs[name]))
        edge = {RISING: line.Edge.RISING, FALLING: line.Edge.FALLING, None: line.Edge.NONE}[self._edges[name]]
        bias = {PULL_UP: line.Bias.PULL_UP, PULL_DOWN: line.Bias.PULL_DOWN, None: line.Bias.AS_IS}[
            request.bias.get(name)]
        return gpiod.LineSettings(direction=line.Direction.INPUT, edge_detection=edge, bias=bias)

    def _by_chip(self, names: Iterable[str]) -> dict[str, list[tuple[str, int]]]:
        groups: dict[str, list[tuple[str, int]]] = {}
        for name in names:
            path, offset = self._where[name]
            groups.setdefault(path, []).append((name, offset))
        return groups

    def _call(self, names: Sequence[str], action, *args, **kwargs):
        try:
            return action(*args, **kwargs)
        except OSError as exc:
            raise _gpio_error(f"GPIO {', '.join(names)} ({self.consumer})", exc) from exc

    def _check(self, names: Iterable[str]) -> None:
        if self._released:
            raise BusError(f"GPIO lines of {self.consumer} used after release")
        for name in names:
            if name not in self._where:
                raise ValueError(f"GPIO line {name} was not requested by {self.consumer}")

    def set_values(self, values: Mapping[str, int]) -> None:
        """Drive the named outputs: one ``set_values`` (one ioctl) per chip."""
        self._check(values)
        inputs = [name for name in values if name not in self._outputs]
        if inputs:
            raise ValueError(f"GPIO line {inputs[0]} of {self.consumer} is an input; it cannot be driven")
        for path, lines in self._by_chip(values).items():
            self._call([name for name, _ in lines], self._requests[path].set_values,
                       {offset: _value(values[name]) for name, offset in lines})

    def get_values(self, names: Sequence[str] | None = None) -> dict[str, int]:
        """Read the named lines (all by default) as 0 or 1: one ``get_values`` per chip."""
        names = list(self.names if names is None else names)
        self._check(names)
        levels: dict[str, int] = {}
        for path, lines in self._by_chip(names).items():
            values = self._call([name for name, _ in lines], self._requests[path].get_values,
                                [offset for _, offset in lines])
            for (name, _), value in zip(lines, values, strict=True):
                levels[name] = int(value == gpiod.line.Value.ACTIVE)
        return {name: levels[name] for name in names}

    def wait_edge(self, name: str, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for the edge ``name`` was requested with; True if it came.

        Edges of the chip's other lines read meanwhile are counted, and returned
        by those lines' next :meth:`wait_edge` (as the kernel's queue would).
        """
        path = self._edge_input(name)
        deadline = time.monotonic() + timeout_s
        while not self._pending[name]:
            if not self._read_events(name, path, max(0.0, deadline - time.monotonic())):
                return False
        self._pending[name] -= 1
        return True

    def drain_edges(self, name: str) -> int:
        """Read the kernel's queue empty without blocking, then forget ``name``'s edges; returns how many."""
        path = self._edge_input(name)
        while self._read_events(name, path, 0.0):
            pass
        drained, self._pending[name] = self._pending[name], 0
        return drained

    def _edge_input(self, name: str) -> str:
        """The chip path of ``name``, refused unless it is an input with edge detection."""
        self._check([name])
        if self._edges.get(name) is None:
            raise ValueError(f"GPIO line {name} of {self.consumer} was not requested with edge detection")
        return self._where[name][0]

    def _read_events(self, name: str, path: str, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for events on chip ``path`` and count each for its line; False if none came."""
        request = self._requests[path]
        if not self._call([name], request.wait_edge_events, timedelta(seconds=timeout_s)):
            return False
        for event in self._call([name], request.read_edge_events):
            self._pending[self._line_at[path, event.line_offset]] += 1
        return True

    def release(self) -> None:
        """Give every chip's request back; idempotent."""
        requests, self._requests = self._requests, {}
        self._released = True
        for request in requests.values():
            request.release()


def _value(level: int):
    return gpiod.line.Value.ACTIVE if level else gpiod.line.Value.INACTIVE
