"""The bus interfaces every chip driver is written against, and the board that hands them out.

A chip driver never opens hardware: it is given an :class:`SPIDevice`, an
:class:`I2CBus` or a :class:`GPIOLines` by a :class:`Board` (as gpiozero devices
are given pins by a pin factory). Two boards implement this module:
``drivers.linux_board`` over gpiod, spidev and smbus2, and ``drivers.emulated`` over
register-level chip emulators. Time also comes from the board (:attr:`Board.clock`),
so settling waits run in simulated time under emulation.

Descendants *must* override the abstract methods; they *may* override the SMBus
helpers of :class:`I2CBus` with native calls that do the same transfers.

>>> from appliance.drivers.emulated.buses import EmulatedI2CBus
>>> from appliance.drivers.emulated.clock import SimulatedClock
>>> bus = EmulatedI2CBus(1, SimulatedClock())
>>> bus.read_byte(0x48)
Traceback (most recent call last):
...
appliance.errors.TransferFailed: [Errno 121] I2C bus 1 address 0x48: no acknowledge (no device answers there)
"""

from __future__ import annotations

import errno
import logging
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TypeVar

from appliance.errors import BusInUse, DeviceMissing, TransferFailed

log = logging.getLogger(__name__)

T = TypeVar("T")

RISING = "rising"
FALLING = "falling"
EDGES = (RISING, FALLING)
PULL_UP = "pull-up"
PULL_DOWN = "pull-down"
BIASES = (PULL_UP, PULL_DOWN)


class Clock:
    """Monotonic time in seconds and a way to wait; the real one sleeps."""

    def monotonic(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)


class SPIDevice(ABC):
    """One chip select on an SPI bus, opened with the mode and clock its chip needs.

    Attributes
    ----------
    name : str
        The device node it stands for, such as ``"/dev/spidev0.1"``.
    mode : int
        SPI mode 0..3 (CPOL << 1 | CPHA).
    max_speed_hz : int
    """

    name: str
    mode: int
    max_speed_hz: int

    @abstractmethod
    def transfer(self, data: bytes) -> bytes:
        """Clock ``data`` out in one chip-select frame; return the bytes clocked in meanwhile.

        Raises :class:`~appliance.errors.TransferFailed` naming the device.
        """

    def close(self) -> None:
        """Give the device back; idempotent."""


class I2CBus(ABC):
    """One I2C adapter; every call names the 7-bit address of the chip it talks to.

    The three primitives are whole I2C transactions (a write message, a read
    message, and a write then a read joined by a repeated start). The SMBus
    helpers below are those transactions under the names datasheets use.
    """

    name: str

    @abstractmethod
    def write(self, address: int, data: bytes) -> None:
        """One write message of ``data`` to ``address``."""

    @abstractmethod
    def read(self, address: int, n: int) -> bytes:
        """One read message of ``n`` bytes from ``address``."""

    @abstractmethod
    def write_read(self, address: int, data: bytes, n: int) -> bytes:
        """Write ``data``, repeated start, read ``n`` bytes: one transaction."""

    def write_byte(self, address: int, value: int) -> None:
        """SMBus send byte: one data byte and no register (the MCP4017's only write)."""
        self.write(address, bytes([value]))

    def read_byte(self, address: int) -> int:
        """SMBus receive byte."""
        return self.read(address, 1)[0]

    def write_byte_data(self, address: int, register: int, value: int) -> None:
        """SMBus write byte: register then value."""
        self.write(address, bytes([register, value]))

    def read_byte_data(self, address: int, register: int) -> int:
        """SMBus read byte: register, repeated start, one byte."""
        return self.write_read(address, bytes([register]), 1)[0]

    def write_word_swapped(self, address: int, register: int, value: int) -> None:
        """A 16-bit register written most significant byte first: register, MSB, LSB.

        On the wire an SMBus write word with its bytes swapped (SMBus sends the low byte first), as Linux's
        ``i2c_smbus_write_word_swapped``; for chips such as the ADS1115 and the MCP9808.
        """
        self.write(address, bytes([register, value >> 8, value & 0xFF]))

    def read_word_swapped(self, address: int, register: int) -> int:
        """A 16-bit register read most significant byte first: register, repeated start, MSB, LSB."""
        high, low = self.write_read(address, bytes([register]), 2)
        return high << 8 | low

    def write_block(self, address: int, register: int, data: bytes) -> None:
        """I2C block write: register then the bytes (a 16-bit register is sent MSB first by the caller)."""
        self.write(address, bytes([register]) + bytes(data))

    def read_block(self, address: int, register: int, n: int) -> bytes:
        """I2C block read: register, repeated start, ``n`` bytes."""
        return self.write_read(address, bytes([register]), n)

    def close(self) -> None:
        """Give the adapter back; idempotent."""


class GPIOLines(ABC):
    """A set of GPIO lines requested together by header name ("GPIO17").

    Outputs change together in one call (one ioctl on Linux), so address and
    strobe lines move at the same instant.
    """

    names: tuple[str, ...]

    @abstractmethod
    def set_values(self, values: Mapping[str, int]) -> None:
        """Drive the named output lines to 0 or 1, all at once."""

    @abstractmethod
    def get_values(self, names: Sequence[str] | None = None) -> dict[str, int]:
        """Read the named lines (all of them by default) as 0 or 1."""

    @abstractmethod
    def wait_edge(self, name: str, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for the edge the input ``name`` was requested with.

        Returns True if it came, False on timeout. Edges are queued from the request on, so one that
        came before this call (and was not taken by an earlier wait) returns at once.
        """

    @abstractmethod
    def drain_edges(self, name: str) -> int:
        """Discard the edges of the input ``name`` queued so far, so the next wait sees only newer ones.

        Returns how many there were.
        """

    def release(self) -> None:
        """Give the lines back; idempotent."""


@dataclass(frozen=True)
class LineRequest:
    """What a driver asks of its GPIO lines: outputs with their first values, inputs with an edge.

    ``bias`` gives inputs the SoC's internal pull-up or pull-down: an open-drain output wired to an
    input only pulls low, and without a pull-up the line floats.
    """

    outputs: Mapping[str, int]
    inputs: Mapping[str, str | None]
    bias: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self):
        clash = set(self.outputs) & set(self.inputs)
        if clash:
            raise ValueError(f"GPIO line {sorted(clash)[0]} requested as both input and output")
        for name, edge in self.inputs.items():
            if edge is not None and edge not in EDGES:
                raise ValueError(f"GPIO line {name}: edge must be one of {EDGES} or None, got {edge!r}")
        for name, bias in self.bias.items():
            if name not in self.inputs:
                raise ValueError(f"GPIO line {name}: a bias is for inputs, and it is not requested as one")
            if bias not in BIASES:
                raise ValueError(f"GPIO line {name}: bias must be one of {BIASES}, got {bias!r}")

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.outputs) + tuple(self.inputs)


class Board(ABC):
    """Hands out the buses of one front end and owns them; a context manager.

    The board reserves what it hands out: asking twice for one chip select or
    GPIO line raises :class:`~appliance.errors.BusInUse` naming the holder.
    """

    clock: Clock

    def __init__(self):
        self._holders: dict[str, str] = {}
        self._opened: list = []

    @abstractmethod
    def _open_spi(self, bus: int, chip_select: int, mode: int, max_speed_hz: int) -> SPIDevice:
        """Open one SPI chip select (descendants override)."""

    @abstractmethod
    def _open_i2c(self, bus: int) -> I2CBus:
        """Open one I2C adapter (descendants override)."""

    @abstractmethod
    def _request_lines(self, request: LineRequest, consumer: str) -> GPIOLines:
        """Request GPIO lines (descendants override)."""

    def spi(self, bus: int, chip_select: int, *, mode: int, max_speed_hz: int, consumer: str) -> SPIDevice:
        """The SPI device at ``bus``/``chip_select`` for ``consumer`` (a chip's name)."""
        if mode not in (0, 1, 2, 3):
            raise ValueError(f"SPI mode must be 0..3, got {mode!r}")
        keys = [f"spi{bus}.{chip_select}"]
        self._reserve(keys, consumer)
        return self._track(self._opening(keys, lambda: self._open_spi(bus, chip_select, mode, max_speed_hz)))

    def i2c(self, bus: int) -> I2CBus:
        """The I2C adapter ``bus``; several chips share it, each at its own address."""
        key = f"i2c{bus}"
        for device in self._opened:
            if getattr(device, "key", None) == key:
                return device
        device = self._open_i2c(bus)
        device.key = key            # type: ignore[attr-defined]  # a tag for the lookup above, on any adapter
        return self._track(device)

    def gpio(self, request: LineRequest, *, consumer: str) -> GPIOLines:
        """Request the lines of ``request`` for ``consumer``."""
        self._reserve(request.names, consumer)
        return self._track(self._opening(request.names, lambda: self._request_lines(request, consumer)))

    def _opening(self, keys, open_device):
        """Open a reserved device; if that fails, give the reservation back so a retry can have it."""
        try:
            return open_device()
        except BaseException:
            for key in keys:
                self._holders.pop(key, None)
            raise

    def _reserve(self, keys: Iterable[str], consumer: str) -> None:
        keys = list(keys)
        for key in keys:
            if key in self._holders:
                raise BusInUse(f"{key} is already in use by {self._holders[key]}; {consumer} cannot have it")
        for key in keys:
            self._holders[key] = consumer

    def _track(self, device: T) -> T:
        self._opened.append(device)
        return device

    def close(self) -> None:
        """Release everything handed out; idempotent."""
        for device in reversed(self._opened):
            (device.release if isinstance(device, GPIOLines) else device.close)()
        self._opened.clear()
        self._holders.clear()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def os_error_to_bus_error(where: str, exc: OSError) -> Exception:
    """The appliance error for an OSError raised by a bus call at ``where`` (device, address or line)."""
    number = exc.errno
    if isinstance(exc, FileNotFoundError) or number == errno.ENOENT:
        return DeviceMissing(f"{where}: {exc.strerror or exc}")
    if number == errno.EBUSY:
        return BusInUse(f"{where}: busy, held by another program or a kernel driver")
    if number == errno.EREMOTEIO:
        return TransferFailed(number, f"{where}: no acknowledge (no device answers there)")
    return TransferFailed(number if number is not None else errno.EIO, f"{where}: {exc.strerror or exc}")


def with_retries(action: Callable[[], T], *, attempts: int, what: str,
                 on_retry: Callable[[int, TransferFailed], None] | None = None) -> T:
    """Run ``action``, repeating it after a :class:`TransferFailed` up to ``attempts`` times in all.

    Transient bus errors (a NACK from a chip busy converting, electrical noise on
    a long cable) are common; a failure that persists is re-raised, naming ``what``.
    """
    for attempt in range(1, attempts):
        try:
            return action()
        except TransferFailed as exc:
            log.warning("%s: transfer failed (attempt %d of %d): %s", what, attempt, attempts, exc.strerror)
            if on_retry is not None:
                on_retry(attempt, exc)
    try:
        return action()
    except TransferFailed as exc:
        raise TransferFailed(exc.errno, f"{what}: failed {attempts} times; last: {exc.strerror}") from exc
