"""A daisy chain of ADG1414 octal switches behind one chip select, and the 74HC154 chip-select decoder.

The chain (facts as in :mod:`appliance.drivers.adg1414`) takes SPI modes 1 and 2
at up to 50 MHz alone and 11 MHz chained. Its shift register is the chips'
words in a row: a frame shifts its bytes in at chip 0 and the old contents out
of the farthest chip's SDO (returned as the read-back), and /SYNC rising
latches what each chip then holds. A frame of another length than the chain
would latch words one or more chips away from where they were meant: an
:class:`EmulatorViolation`, as is any latched state the board's ``validate``
refuses (the drive matrix refuses an electrode on both buses and a second
electrode on a bus). Power-on: every switch off.

The decoder routes each frame of its chip select to the chip on the output the
address lines select; an output with no chip leaves MISO to its pull-up (0xFF).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

from appliance.drivers.adg1414 import DAISY_MAX_SPEED_HZ, ELECTRODES_PER_CHIP
from appliance.drivers.emulated.buses import EmulatorViolation, GPIOBank, SPIChipEmulator, notify


def drive_of(words: Sequence[int]) -> tuple[int | None, int | None]:
    """The (0-based) electrodes the drive matrix's words put on the I+ and I- buses (None for an empty bus).

    Refuses an electrode on both buses (it would short the current source, no current reaching the
    mat while the readings look like an open drive) and a second electrode on a bus (the current
    would divide between them in proportions nobody knows).
    """
    buses: tuple[list[int], list[int]] = ([], [])
    for chip, word in enumerate(words):
        for j in range(ELECTRODES_PER_CHIP):
            electrode = chip * ELECTRODES_PER_CHIP + j
            on = (word >> 2 * j) & 3
            if on == 3:
                raise EmulatorViolation(f"drive matrix: electrode {electrode + 1} switched to both current buses")
            if on:
                buses[on - 1].append(electrode)
    for name, bus in zip(("I+", "I-"), buses):
        if len(bus) > 1:
            raise EmulatorViolation(f"drive matrix: electrodes {', '.join(str(e + 1) for e in bus)} all on the "
                                    f"{name} bus; the current would divide between them")
    source, sink = (bus[0] if bus else None for bus in buses)
    return source, sink


class EmulatedADG1414Chain(SPIChipEmulator):
    """``chips`` ADG1414s; ``validate(words)`` may refuse a latched state (raise EmulatorViolation)."""

    name = "ADG1414 chain"
    modes = frozenset({1, 2})

    def __init__(self, chips: int, *, validate: Callable[[list[int]], object] | None = None):
        self.chips = chips
        self.max_speed_hz = 50_000_000 if chips == 1 else DAISY_MAX_SPEED_HZ
        self.validate = validate
        self.listeners: list[Callable[[], None]] = []
        self.words = [0] * chips
        self.frames = 0

    def reset(self) -> None:
        """Power-on: every switch off."""
        changed = any(self.words)
        self.words = [0] * self.chips
        if changed:
            notify(self.listeners)

    def check_frame(self, data: bytes) -> None:
        if len(data) != self.chips:
            raise EmulatorViolation(f"ADG1414 chain of {self.chips} chips: a frame of {len(data)} bytes would latch "
                                    f"each word {abs(len(data) - self.chips)} chip(s) away from its own")

    def frame(self, data: bytes) -> bytes:
        out = bytes(reversed(self.words))
        new = list(reversed(data))
        if self.validate is not None:
            self.validate(new)
        changed = new != self.words
        self.words = new
        self.frames += 1
        if changed:
            notify(self.listeners)
        return out

    def closed(self, chip: int, switch: int) -> bool:
        """Whether switch S(switch + 1) of chip ``chip`` is on."""
        return bool(self.words[chip] >> switch & 1)


class EmulatedChipSelectDecoder(SPIChipEmulator):
    """74HC154s enabled by one chip select; ``chips`` maps decoder outputs to the chips on them."""

    name = "74HC154 chip-select decoder"

    def __init__(self, bank: GPIOBank, address_lines: Sequence[str], chips: Mapping[int, SPIChipEmulator]):
        if not chips:
            raise ValueError("a decoder with no chips on it")
        self.bank, self.address_lines, self.chips = bank, tuple(address_lines), dict(chips)
        self.modes = frozenset.intersection(*(frozenset(chip.modes) for chip in self.chips.values()))
        self.max_speed_hz = min(chip.max_speed_hz for chip in self.chips.values())
        self.selections: list[int] = []

    def selected(self) -> int:
        """The output the address lines select now."""
        return sum(self.bank.driven.get(name, 0) << bit for bit, name in enumerate(self.address_lines))

    def check_frame(self, data: bytes) -> None:
        chip = self.chips.get(self.selected())
        if chip is not None:
            chip.check_frame(data)

    def frame(self, data: bytes) -> bytes:
        index = self.selected()
        self.selections.append(index)
        chip = self.chips.get(index)
        return b"\xff" * len(data) if chip is None else chip.frame(data)

    def reset(self) -> None:
        for chip in self.chips.values():
            chip.reset()
