"""ADG1414 octal SPST switches, daisy-chained, and the drive switch matrix they make.

Facts used, from the ADG1414 data sheet (Rev. B): eight switches per chip, one
8-bit word each (a 1 closes the switch; bit n is switch S(n+1) [recall: verify
the bit order]); words are latched when /SYNC rises; SDO passes the shift
register on, so a chain of N chips takes one frame of N words, the word for
the chip farthest from the host first (Figure 3). Data is taken on SCLK falling
edges (modes 1 and 2). SCLK may run at 50 MHz alone, but in a chain SDO is
valid only 40 ns after a rising edge (t11, Table 6), which with 5 ns of data
setup caps the chain at 11 MHz. At power-up every switch is off. On
resistance 9.5 ohm at +/-15 V: it sits in the current path only, where the
current source makes it irrelevant.

The drive matrix gives each electrode two switches, one to the current source's
I+ bus and one to its I- bus; chip k carries electrodes 4k+1 to 4k+4 (1-based),
switch 2j to I+ and 2j+1 to I- for its j-th electrode. A drive change is one
frame for the whole chain. The driver refuses what the hardware would do
without complaint and what would mislead: an electrode on both buses (the source
shorted through it), a second electrode on a bus.

>>> DriveMatrix.words_for(3, 6, n_chips=2)
[16, 8]
"""

from __future__ import annotations

from collections.abc import Sequence

from appliance.drivers.bus import SPIDevice

ELECTRODES_PER_CHIP = 4
DAISY_MAX_SPEED_HZ = 11_000_000


class ADG1414Chain:
    """``chips`` ADG1414s daisy-chained on one chip select; chip 0 is the one nearest the host's MOSI."""

    SPI_MODE = 1
    """Data is taken on SCLK falling edges; mode 2 would do as well."""
    MAX_SPEED_HZ = 50_000_000

    def __init__(self, spi: SPIDevice, chips: int):
        if chips < 1:
            raise ValueError(f"an ADG1414 chain needs at least one chip, got {chips}")
        self.spi, self.chips = spi, chips
        self._words: list[int] | None = None

    @classmethod
    def speed_limit_hz(cls, chips: int) -> int:
        """The fastest SCLK for a chain of ``chips``: SDO's 40 ns delay limits a chain."""
        return cls.MAX_SPEED_HZ if chips == 1 else DAISY_MAX_SPEED_HZ

    def write(self, words: Sequence[int]) -> bytes:
        """Set every chip's switches (``words[k]`` for chip k) in one frame; returns what SDO shifted out:
        the previous words, farthest chip first (the chain's read-back, when SDO is wired back)."""
        words = list(words)
        if len(words) != self.chips:
            raise ValueError(f"an ADG1414 chain of {self.chips} chips takes {self.chips} words, got {len(words)}")
        for k, word in enumerate(words):
            if isinstance(word, bool) or not isinstance(word, int) or not 0 <= word <= 0xFF:
                raise ValueError(f"ADG1414 {k}: switch word {word!r} is not 0..255")
        received = self.spi.transfer(bytes(reversed(words)))
        self._words = words
        return received

    def off(self) -> None:
        """Open every switch."""
        self.write([0] * self.chips)

    @property
    def words(self) -> list[int] | None:
        """The words last written (None before any, or after :meth:`forget`)."""
        return None if self._words is None else list(self._words)

    def forget(self) -> None:
        self._words = None


class DriveMatrix:
    """The I+ / I- switch of every electrode on an :class:`ADG1414Chain`; electrodes are 1-based."""

    def __init__(self, chain: ADG1414Chain, n_electrodes: int):
        if chain.chips * ELECTRODES_PER_CHIP < n_electrodes:
            raise ValueError(f"{chain.chips} ADG1414s switch {chain.chips * ELECTRODES_PER_CHIP} electrodes, "
                             f"not {n_electrodes}")
        self.chain, self.n_electrodes = chain, n_electrodes
        self.pair: tuple[int, int] | None = None

    @staticmethod
    def chips_for(n_electrodes: int) -> int:
        return -(-n_electrodes // ELECTRODES_PER_CHIP)

    @staticmethod
    def words_for(pos: int, neg: int, *, n_chips: int) -> list[int]:
        """The chain's words that put electrode ``pos`` on I+ and ``neg`` on I- and every other switch off."""
        words = [0] * n_chips
        for electrode, bus in ((pos, 0), (neg, 1)):
            chip, j = divmod(electrode - 1, ELECTRODES_PER_CHIP)
            words[chip] |= 1 << (2 * j + bus)
        return words

    def route(self, pos: int, neg: int) -> None:
        """Current into ``pos`` and out of ``neg``: one transfer; nothing if already routed."""
        for e in (pos, neg):
            if isinstance(e, bool) or not isinstance(e, int) or not 1 <= e <= self.n_electrodes:
                raise ValueError(f"drive electrode {e!r} is not one of 1..{self.n_electrodes}")
        if pos == neg:
            raise ValueError(f"drive pair {pos}-{neg}: one electrode on both buses would short the current source")
        if (pos, neg) == self.pair:
            return
        self.chain.write(self.words_for(pos, neg, n_chips=self.chain.chips))
        self.pair = (pos, neg)

    def off(self) -> None:
        self.chain.off()
        self.pair = None

    def forget(self) -> None:
        self.chain.forget()
        self.pair = None
