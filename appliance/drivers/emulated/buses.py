"""Fake buses that route each transfer to a chip emulator, log it, and charge its time.

The fakes implement the interfaces of :mod:`appliance.drivers.bus` and reject
what real hardware would reject: an I2C address nobody answers at gives
``TransferFailed`` with errno 121 (as smbus2 gives OSError 121 on a Pi), a chip
select with no chip behind it cannot be opened, a GPIO line that was not
requested cannot be driven. A driver that breaks a chip's bus protocol (wrong SPI
mode, frame length or clock) gets an :class:`EmulatorViolation`: real hardware
would silently misread such a frame, and a test must not.

Faults are injected through a :class:`FaultPlan` shared by the buses.
"""

from __future__ import annotations

import errno
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

from appliance.drivers.bus import (FALLING, PULL_UP, RISING, GPIOLines, I2CBus, LineRequest, SPIDevice,
                                   os_error_to_bus_error)
from appliance.drivers.emulated.clock import SimulatedClock


class EmulatorViolation(AssertionError):
    """A driver used a chip in a way its datasheet forbids (wrong SPI mode, length, clock, sequence)."""


@dataclass(frozen=True)
class Transaction:
    """One logged bus operation.

    ``kind`` is ``"spi"``, ``"i2c-write"``, ``"i2c-read"``, ``"i2c-write-read"`` or
    ``"gpio"``; ``target`` the device node, ``"i2c1@0x48"`` or the line names.
    """

    time_s: float
    kind: str
    target: str
    sent: bytes = b""
    received: bytes = b""


@dataclass(frozen=True)
class BusTiming:
    """How long a transfer takes: bit time on the wire plus the cost of one call from Python."""

    i2c_clock_hz: float = 400_000.0
    call_overhead_s: float = 50e-6

    def i2c_s(self, n_bytes: int, n_messages: int = 1) -> float:
        """Each message carries its address byte; every byte is 9 clocks (8 bits and the acknowledge)."""
        return (n_bytes + n_messages) * 9 / self.i2c_clock_hz + self.call_overhead_s

    def spi_s(self, n_bytes: int, speed_hz: float) -> float:
        return 8 * n_bytes / speed_hz + self.call_overhead_s


@dataclass
class FaultPlan:
    """Transfer faults to inject: the next ``count`` transfers to a target fail with ``errno``.

    Targets are ``"i2c1@0x48"`` or a device node such as ``"/dev/spidev0.1"``.
    ``missing`` lists device nodes that do not exist when the board opens them.
    """

    failures: dict[str, list[int | None]] = field(default_factory=dict)
    missing: set[str] = field(default_factory=set)

    def fail_next(self, target: str, count: int = 1, error: int = errno.EREMOTEIO, *, after: int = 0) -> None:
        """The ``count`` transfers to ``target`` that follow the next ``after`` ones fail."""
        self.failures.setdefault(target, []).extend([None] * after + [error] * count)

    def check(self, target: str) -> None:
        """Raise the OSError queued for ``target``, if any."""
        queued = self.failures.get(target)
        if queued:
            number = queued.pop(0)
            if number is not None:
                raise OSError(number, errno.errorcode.get(number, "error"))

    def clear(self) -> None:
        self.failures.clear()
        self.missing.clear()


def notify(listeners) -> None:
    """Tell each listener (the analogue chain) that an emulated chip's analogue state changed."""
    for listener in list(listeners):
        listener()


class SPIChipEmulator:
    """Base of an SPI chip emulator: its accepted modes, clock limit and frame handling."""

    name = "spi chip"
    modes: frozenset[int] = frozenset({0})
    max_speed_hz = 10_000_000

    def check_frame(self, data: bytes) -> None:
        """Raise :class:`EmulatorViolation` for a frame the chip cannot take (override)."""

    def frame(self, data: bytes) -> bytes:
        """Take one chip-select frame; return what the chip drives on MISO meanwhile."""
        raise NotImplementedError

    def reset(self) -> None:
        """Return to the power-on state."""


class I2CChipEmulator:
    """Base of an I2C chip emulator at one 7-bit address.

    ``write`` and ``read`` may raise ``OSError(errno.EREMOTEIO)`` where the chip
    does not acknowledge a byte.
    """

    name = "i2c chip"
    address = 0x00

    def write(self, data: bytes) -> None:
        raise NotImplementedError

    def read(self, n: int) -> bytes:
        raise NotImplementedError

    def write_read(self, data: bytes, n: int) -> bytes:
        """A write joined to a read by a repeated start; most chips treat it as write then read."""
        self.write(data)
        return self.read(n)

    def reset(self) -> None:
        """Return to the power-on state."""


class EmulatedSPIDevice(SPIDevice):
    """One chip select wired to one chip emulator."""

    def __init__(self, name: str, mode: int, max_speed_hz: int, chip: SPIChipEmulator, clock: SimulatedClock,
                 timing: BusTiming, log: list[Transaction], faults: FaultPlan):
        self.name, self.mode, self.max_speed_hz = name, mode, max_speed_hz
        self.chip, self._clock, self._timing, self._log, self._faults = chip, clock, timing, log, faults
        self.closed = False

    def transfer(self, data: bytes) -> bytes:
        if self.closed:
            raise EmulatorViolation(f"{self.name}: transfer after close")
        data = bytes(data)
        if self.mode not in self.chip.modes:
            raise EmulatorViolation(f"{self.chip.name} on {self.name}: SPI mode {self.mode} is not one the chip "
                                    f"latches correctly (it needs {sorted(self.chip.modes)})")
        if self.max_speed_hz > self.chip.max_speed_hz:
            raise EmulatorViolation(f"{self.chip.name} on {self.name}: clock {self.max_speed_hz} Hz exceeds "
                                    f"the chip's {self.chip.max_speed_hz} Hz")
        self._clock.sleep(self._timing.spi_s(len(data), self.max_speed_hz))
        try:
            self._faults.check(self.name)
        except OSError as exc:
            raise os_error_to_bus_error(f"SPI {self.name}", exc) from None
        self.chip.check_frame(data)
        received = self.chip.frame(data)
        self._log.append(Transaction(self._clock.monotonic(), "spi", self.name, data, received))
        return received

    def close(self) -> None:
        self.closed = True


class EmulatedI2CBus(I2CBus):
    """An I2C adapter with chip emulators attached at their addresses."""

    def __init__(self, number: int, clock: SimulatedClock, timing: BusTiming | None = None,
                 log: list[Transaction] | None = None, faults: FaultPlan | None = None):
        self.number = number
        self.name = f"/dev/i2c-{number}"
        self.chips: dict[int, I2CChipEmulator] = {}
        self._clock = clock
        self._timing = timing or BusTiming()
        self.log = log if log is not None else []
        self._faults = faults or FaultPlan()

    def attach(self, chip: I2CChipEmulator) -> None:
        if chip.address in self.chips:
            raise ValueError(f"I2C address 0x{chip.address:02X} already has {self.chips[chip.address].name}")
        self.chips[chip.address] = chip

    def _transact(self, kind: str, address: int, sent: bytes, n_read: int, n_messages: int,
                  action: Callable[[I2CChipEmulator], bytes]) -> bytes:
        target = f"i2c{self.number}@0x{address:02X}"
        self._clock.sleep(self._timing.i2c_s(len(sent) + n_read, n_messages))
        try:
            self._faults.check(target)
            chip = self.chips.get(address)
            if chip is None:
                raise OSError(errno.EREMOTEIO, "Remote I/O error")
            received = action(chip)
        except OSError as exc:
            self.log.append(Transaction(self._clock.monotonic(), kind + "-nack", target, sent))
            raise os_error_to_bus_error(f"I2C bus {self.number} address 0x{address:02X}", exc) from None
        self.log.append(Transaction(self._clock.monotonic(), kind, target, sent, received))
        return received

    def write(self, address: int, data: bytes) -> None:
        data = bytes(data)

        def write(chip: I2CChipEmulator) -> bytes:
            chip.write(data)
            return b""

        self._transact("i2c-write", address, data, 0, 1, write)

    def read(self, address: int, n: int) -> bytes:
        return self._transact("i2c-read", address, b"", n, 1, lambda chip: _exactly(chip.read(n), n, chip))

    def write_read(self, address: int, data: bytes, n: int) -> bytes:
        data = bytes(data)
        return self._transact("i2c-write-read", address, data, n, 2,
                              lambda chip: _exactly(chip.write_read(data, n), n, chip))


def _exactly(data: bytes, n: int, chip: I2CChipEmulator) -> bytes:
    if len(data) != n:
        raise AssertionError(f"emulated {chip.name} returned {len(data)} bytes for a read of {n}")
    return bytes(data)


class InputSource:
    """What drives an emulated input line: a level now, and the edges it made and will make.

    ``open_drain`` sources only pull low: their line reads high through a pull-up, or floats.
    """

    name = "input source"
    open_drain = False

    def level(self, now: float) -> int:
        raise NotImplementedError

    def next_edge(self, after: float, edge: str) -> float | None:
        """The time of the first ``edge`` later than ``after``, past or scheduled, or None if none is known.

        The line's reader asks with ``after`` never going back, so a source may forget older edges.
        """
        raise NotImplementedError


class GPIOBank:
    """The header's lines: outputs the appliance drives (watched by emulated chips) and inputs chips drive."""

    def __init__(self, clock: SimulatedClock, names: Sequence[str], log: list[Transaction]):
        self.clock = clock
        self.log = log
        self.names = frozenset(names)
        self.driven: dict[str, int] = {}
        self.sources: dict[str, InputSource] = {}
        self.watchers: dict[str, list[Callable[[int, int], None]]] = {}
        self.broken: dict[str, int] = {}          # line -> the errno a write to it fails with

    def break_line(self, name: str, error: int = errno.EIO) -> None:
        """Writes to ``name`` fail with ``error`` (a line shorted, or its chip gone) until :meth:`mend_line`."""
        self.broken[name] = error

    def mend_line(self, name: str) -> None:
        self.broken.pop(name, None)

    def watch(self, name: str, callback: Callable[[int, int], None]) -> None:
        """Call ``callback(old, new)`` whenever the appliance drives ``name`` (wired to a chip pin)."""
        self.watchers.setdefault(name, []).append(callback)

    def connect(self, name: str, source: InputSource) -> None:
        """Wire a chip output pin to the input line ``name``."""
        self.sources[name] = source

    def drive(self, values: Mapping[str, int]) -> None:
        changes = []
        for name, value in values.items():
            old = self.driven.get(name, 0)
            self.driven[name] = value
            if old != value:
                changes.append((name, old, value))
        for name, old, value in changes:
            for callback in self.watchers.get(name, ()):
                callback(old, value)

    def level(self, name: str) -> int:
        source = self.sources.get(name)
        if source is None:
            return self.driven.get(name, 0)
        return source.level(self.clock.monotonic())


class EmulatedGPIOLines(GPIOLines):
    """Lines of a :class:`GPIOBank` requested by one consumer.

    Each edge input keeps the kernel's queue: edges from the request on stay pending until a
    wait takes them or a drain discards them, however long ago they came.
    """

    def __init__(self, bank: GPIOBank, request: LineRequest, consumer: str, timing: BusTiming):
        unknown = [n for n in request.names if n not in bank.names]
        if unknown:
            from appliance.errors import DeviceMissing

            raise DeviceMissing(f"GPIO line {unknown[0]} (for {consumer}) does not exist on this board")
        self.bank, self.request, self.consumer, self._timing = bank, request, consumer, timing
        self.names = request.names
        self.released = False
        self._taken_until = dict.fromkeys(request.inputs, bank.clock.monotonic())   # edges up to here are gone
        bank.drive({name: int(bool(v)) for name, v in request.outputs.items()})

    def _check(self, names) -> None:
        if self.released:
            raise EmulatorViolation(f"GPIO lines of {self.consumer} used after release")
        for name in names:
            if name not in self.names:
                raise EmulatorViolation(f"GPIO line {name} was not requested by {self.consumer}")
            source = self.bank.sources.get(name)
            if source is not None and source.open_drain and self.request.bias.get(name) != PULL_UP:
                raise EmulatorViolation(f"GPIO line {name} of {self.consumer}: {source.name} drives it open drain "
                                        "and nothing pulls it up; request it with the pull-up bias")

    def set_values(self, values: Mapping[str, int]) -> None:
        self._check(values)
        inputs = [n for n in values if n in self.request.inputs]
        if inputs:
            raise EmulatorViolation(f"GPIO line {inputs[0]} of {self.consumer} is an input; it cannot be driven")
        self.bank.clock.sleep(self._timing.call_overhead_s)
        broken = [n for n in values if n in self.bank.broken]
        if broken:                                  # as the kernel's line-set ioctl fails: nothing changes
            error = self.bank.broken[broken[0]]
            raise OSError(error, f"GPIO line {broken[0]} of {self.consumer}: {os.strerror(error)}")
        values = {name: int(bool(v)) for name, v in values.items()}
        self.bank.log.append(Transaction(self.bank.clock.monotonic(), "gpio", ",".join(values),
                                         bytes(values.values())))
        self.bank.drive(values)

    def get_values(self, names: Sequence[str] | None = None) -> dict[str, int]:
        names = list(self.names if names is None else names)
        self._check(names)
        self.bank.clock.sleep(self._timing.call_overhead_s)
        return {name: self.bank.level(name) for name in names}

    def wait_edge(self, name: str, timeout_s: float) -> bool:
        self._check_edge_input(name)
        clock = self.bank.clock
        clock.sleep(self._timing.call_overhead_s)      # the wait is a call too: its events are read by ioctl
        when = self._next_edge(name)
        if when is not None and when <= clock.monotonic() + timeout_s:
            clock.sleep(max(0.0, when - clock.monotonic()))
            self._taken_until[name] = when
            return True
        clock.sleep(timeout_s)
        return False

    def drain_edges(self, name: str) -> int:
        self._check_edge_input(name)
        self.bank.clock.sleep(self._timing.call_overhead_s)
        now, drained = self.bank.clock.monotonic(), 0
        while (when := self._next_edge(name)) is not None and when <= now:
            self._taken_until[name], drained = when, drained + 1
        self._taken_until[name] = now
        return drained

    def _check_edge_input(self, name: str) -> None:
        self._check([name])
        if self.request.inputs.get(name) not in (RISING, FALLING):
            raise EmulatorViolation(f"GPIO line {name} of {self.consumer} was not requested with edge detection")

    def _next_edge(self, name: str) -> float | None:
        """When the first edge of ``name`` not yet taken came or will come; None if none is known."""
        source, edge = self.bank.sources.get(name), self.request.inputs[name]
        assert edge is not None                 # _check_edge_input saw it requested with edge detection
        return None if source is None else source.next_edge(self._taken_until[name], edge)

    def release(self) -> None:
        self.released = True
