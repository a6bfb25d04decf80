"""AD9833 direct digital synthesiser: the sine source of the excitation chain.

The chip takes 16-bit words on SPI mode 2, MSB first. The top bits of each word
pick the register (control, FREQ0/1, PHASE0/1). This driver sends one word per
chip-select frame and keeps bit B28 set in every control word, so a frequency
register is always loaded as two consecutive 14-bit halves (LSBs first) and only
changes after the second: an update while running never produces a
half-written frequency. Public Pi code that writes 0x0000 "for sine" clears B28,
after which a two-word frequency write lands as two single halves and the output
frequency is silently wrong; the emulator detects this.

Only FREQ0 and PHASE0 are used: the appliance needs one steady sine at a time.
"""

from __future__ import annotations

import math

from appliance.drivers.bus import SPIDevice

CONTROL = 0x0000
FREQ0 = 0x4000
PHASE0 = 0xC000

B28 = 1 << 13
RESET = 1 << 8
SLEEP1 = 1 << 7
SLEEP12 = 1 << 6

WAVEFORM_BITS = {"sine": 0x0000, "triangle": 0x0002, "square": 0x0028}
"""Control bits per waveform: MODE (D1) for triangle; OPBITEN (D5) with DIV2 (D3) for a full-rate square."""


class AD9833:
    """One AD9833 on an SPI chip select, clocked at ``mclk_hz``."""

    SPI_MODE = 2
    MAX_SPEED_HZ = 10_000_000
    """Well under the chip's 40 MHz, so long ribbon cables to the front end still work."""

    def __init__(self, spi: SPIDevice, *, mclk_hz: float = 25e6):
        if not mclk_hz > 0:
            raise ValueError(f"AD9833 master clock must be positive, got {mclk_hz!r} Hz")
        self.spi = spi
        self.mclk_hz = float(mclk_hz)
        self._word: int | None = None
        self._waveform = "sine"

    def frequency_word(self, frequency_hz: float) -> int:
        """The 28-bit FREQREG for ``frequency_hz``: round(f * 2**28 / mclk).

        Refuses anything outside (0, mclk/2], the Nyquist limit of the DDS.
        """
        if not (math.isfinite(frequency_hz) and 0 < frequency_hz <= self.mclk_hz / 2):
            raise ValueError(f"AD9833 frequency {frequency_hz!r} Hz is outside (0, {self.mclk_hz / 2:g}] Hz "
                             f"for a {self.mclk_hz:g} Hz master clock")
        return round(frequency_hz * 2**28 / self.mclk_hz)

    def start(self, frequency_hz: float, waveform: str = "sine") -> None:
        """Reset the chip, load FREQ0 and PHASE0 = 0, then leave reset with ``waveform`` on the output."""
        if waveform not in WAVEFORM_BITS:
            raise ValueError(f"AD9833 waveform {waveform!r} is not one of {sorted(WAVEFORM_BITS)}")
        word = self.frequency_word(frequency_hz)
        self._send(CONTROL | B28 | RESET)
        self._send_frequency(word)
        self._send(PHASE0)
        self._send(CONTROL | B28 | WAVEFORM_BITS[waveform])
        self._word, self._waveform = word, waveform

    def set_frequency(self, frequency_hz: float) -> None:
        """Change the running frequency; the register switches over only after its second half."""
        if self._word is None:
            raise RuntimeError("AD9833 is stopped: call start() first (B28 is only known to be set after it)")
        word = self.frequency_word(frequency_hz)
        self._send_frequency(word)
        self._word = word

    def stop(self) -> None:
        """Hold the phase accumulator in reset and power down the MCLK and the DAC: no output."""
        self._send(CONTROL | B28 | RESET | SLEEP1 | SLEEP12)
        self._word = None

    @property
    def frequency_hz(self) -> float | None:
        """The frequency actually produced (FREQREG * mclk / 2**28), or None when stopped."""
        return None if self._word is None else self._word * self.mclk_hz / 2**28

    @property
    def waveform(self) -> str | None:
        """The waveform on the output, or None when stopped."""
        return None if self._word is None else self._waveform

    def _send_frequency(self, word: int) -> None:
        self._send(FREQ0 | (word & 0x3FFF))
        self._send(FREQ0 | (word >> 14))

    def _send(self, word: int) -> None:
        self.spi.transfer(word.to_bytes(2, "big"))
