"""ADG725 and ADG731 emulators: one 8-bit word per /SYNC frame sets the switches.

The datasheet states that on power-up the shift register holds zeros and every
switch is off. The truth table for the control bits is taken as follows
(from datasheet recall and the research notes, to be checked against the
datasheet's truth table before these emulators are treated as a reference):

* EN (bit 7) = 1 turns every switch off, whatever the other bits say.
* With EN = 0, a mux whose chip-select bit is 0 (active low: /CSA bit 6 and /CSB
  bit 5 on the ADG725, /CS bit 6 on the ADG731) connects the addressed channel.
* With EN = 0, a mux whose chip-select bit is 1 keeps its previous switch
  condition: the channel it had, or off if it was off (a mux switched off by
  EN = 1 does not come back on by itself).
* The bits the table marks don't care (bit 4 of the ADG725, bit 5 of the ADG731)
  are ignored.

So EIT-kit's "disable" word 0xC0 | n does turn everything off, through EN.
Both chips latch on SCLK falling edges with SCLK idling either level: SPI modes
1 and 2, up to 30 MHz; a frame of other than 8 bits is an :class:`EmulatorViolation`.
"""

from __future__ import annotations

from collections.abc import Callable

from appliance.drivers.emulated.buses import EmulatorViolation, SPIChipEmulator, notify

EN_OFF = 0x80


class _SerialMux(SPIChipEmulator):
    """Shared frame handling: exactly one byte, listeners told after a change."""

    modes = frozenset({1, 2})
    max_speed_hz = 30_000_000
    _state: dict[str, int | None]           # mux name -> channel, None when off

    def __init__(self):
        self.listeners: list[Callable[[], None]] = []
        self._power_on()

    def _power_on(self) -> None:
        """Set ``self._state`` (mux name -> channel or None) to every switch off."""
        raise NotImplementedError

    def _apply(self, word: int) -> None:
        """Update ``self._state`` from one control word."""
        raise NotImplementedError

    def reset(self) -> None:
        """Power-on state: every switch off."""
        before = dict(self._state)
        self._power_on()
        self._notify_if_changed(before)

    def check_frame(self, data: bytes) -> None:
        if len(data) != 1:
            raise EmulatorViolation(f"{self.name}: a frame of {len(data)} bytes; the chip takes exactly one 8-bit word")

    def frame(self, data: bytes) -> bytes:
        before = dict(self._state)
        self._apply(data[0])
        self._notify_if_changed(before)
        return bytes(len(data))

    def _notify_if_changed(self, before: dict[str, int | None]) -> None:
        if self._state != before:
            notify(self.listeners)


class EmulatedADG725(_SerialMux):
    """Dual 16:1 mux; :meth:`selected` gives the channel of mux ``"A"`` or ``"B"``."""

    name = "ADG725"

    def _power_on(self) -> None:
        self._state = {"A": None, "B": None}

    def _apply(self, word: int) -> None:
        if word & EN_OFF:
            self._state = {"A": None, "B": None}
            return
        address = word & 0x0F
        if not word & 0x40:
            self._state["A"] = address
        if not word & 0x20:
            self._state["B"] = address

    def selected(self, mux: str) -> int | None:
        """The 0-based channel mux ``"A"`` or ``"B"`` connects, or None when it is off."""
        if mux not in self._state:
            raise ValueError(f"ADG725 has muxes 'A' and 'B', not {mux!r}")
        return self._state[mux]


class EmulatedADG731(_SerialMux):
    """32:1 mux; :meth:`selected` gives its channel."""

    name = "ADG731"

    def _power_on(self) -> None:
        self._state = {"D": None}

    def _apply(self, word: int) -> None:
        if word & EN_OFF:
            self._state = {"D": None}
        elif not word & 0x40:
            self._state = {"D": word & 0x1F}

    def selected(self) -> int | None:
        """The 0-based channel connected to the drain, or None when off."""
        return self._state["D"]
