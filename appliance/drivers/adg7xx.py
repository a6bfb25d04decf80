"""ADG725 (dual 16:1) and ADG731 (32:1) serially controlled analogue multiplexers.

Each takes one 8-bit word per chip-select frame, latched when /SYNC rises: bit 7
EN (1 turns every switch off), then chip-select bits that are active low (0 = this
mux takes the address, 1 = it keeps its switch condition), then the address. On
the ADG725 one word carries a single address for whichever of mux A (bit 6, /CSA)
and mux B (bit 5, /CSB) it selects, so two different channels need two frames.

Drivers keep a shadow of what they set (:attr:`ADG725.selection`) and do not
re-send a mux that already holds the requested channel; after a power cycle of
the front end call ``off()`` first so the shadow matches the chip again.
Channels are 0-based (channel n is the datasheet's S(n+1)).
"""

from __future__ import annotations

from appliance.drivers.bus import SPIDevice

ALL_OFF = 0x80
KEEP_A = 0x40
KEEP_B = 0x20


def _check_channel(chip: str, mux: str, channel: int, ways: int) -> None:
    if isinstance(channel, bool) or not isinstance(channel, int) or not 0 <= channel < ways:
        raise ValueError(f"{chip} {mux}channel {channel!r} is out of range 0..{ways - 1}")


class ADG725:
    """Dual 16:1 mux: mux A and mux B, each on one of 16 channels or off."""

    SPI_MODE = 2
    """Data is latched on SCLK falling edges (modes 1 and 2); mode 2, because SPI1 on a Pi 3 or 4 refuses CPHA = 1."""
    MAX_SPEED_HZ = 10_000_000
    """A third of the chip's 30 MHz."""

    def __init__(self, spi: SPIDevice):
        self.spi = spi
        self._a: int | None = None
        self._b: int | None = None

    def select(self, a: int | None, b: int | None) -> None:
        """Put mux A on channel ``a`` and mux B on channel ``b`` (None keeps that mux as it is).

        Sends the fewest frames: none if nothing changes, one if only one mux
        changes or both go to the same channel, two otherwise (A first).
        """
        for mux, channel in (("A", a), ("B", b)):
            if channel is not None:
                _check_channel("ADG725", f"mux {mux} ", channel, 16)
        new_a = a if a is not None and a != self._a else None
        new_b = b if b is not None and b != self._b else None
        if new_a is not None and new_a == new_b:
            self._send(new_a)
        else:
            if new_a is not None:
                self._send(KEEP_B | new_a)
            if new_b is not None:
                self._send(KEEP_A | new_b)
        self._a = self._a if a is None else a
        self._b = self._b if b is None else b

    def off(self) -> None:
        """Turn every switch of both muxes off."""
        self._send(ALL_OFF)
        self._a = self._b = None

    @property
    def selection(self) -> tuple[int | None, int | None]:
        """(channel of mux A, channel of mux B) as last set; None for a mux that is off."""
        return self._a, self._b

    def _send(self, word: int) -> None:
        self.spi.transfer(bytes([word]))


class ADG731:
    """32:1 mux: one of 32 channels or off."""

    SPI_MODE = 2
    """Data is latched on SCLK falling edges (modes 1 and 2); mode 2, because SPI1 on a Pi 3 or 4 refuses CPHA = 1."""
    MAX_SPEED_HZ = 10_000_000
    """A third of the chip's 30 MHz."""

    def __init__(self, spi: SPIDevice):
        self.spi = spi
        self._channel: int | None = None

    def select(self, channel: int) -> None:
        """Connect channel ``channel`` (0..31) to the common drain; nothing is sent if it already is."""
        _check_channel("ADG731", "", channel, 32)
        if channel != self._channel:
            self.spi.transfer(bytes([channel]))
            self._channel = channel

    def off(self) -> None:
        """Turn every switch off."""
        self.spi.transfer(bytes([ALL_OFF]))
        self._channel = None

    @property
    def selection(self) -> int | None:
        """The channel last selected, or None when off."""
        return self._channel
