"""Register-level AD9833 emulator: control, FREQ0/1 and PHASE0/1 behind SPI mode 2.

It decodes each 16-bit word as the chip does, including the B28 rule that makes
the common Pi-code bug visible: with B28 = 1 a frequency register is loaded by
two consecutive writes (14 LSBs, then 14 MSBs, the register changing only after
the second); with B28 = 0 each write replaces the half chosen by HLB. A writer
that sends control 0x0000 "for sine" and then a two-word frequency therefore
gets a wrong frequency, as on the real chip; the emulator also explains it in
:attr:`EmulatedAD9833.warnings`.

Power-on is modelled as control = RESET with every register 0: the datasheet asks
for a reset at power-up and leaves the registers undefined, so output stays off
(``output_hz`` 0.0) until a control word clears RESET.
"""

from __future__ import annotations

from collections.abc import Callable

from appliance.drivers.emulated.buses import EmulatorViolation, SPIChipEmulator, notify

B28, HLB, FSELECT = 1 << 13, 1 << 12, 1 << 11
RESET, SLEEP1, SLEEP12, OPBITEN, DIV2, MODE = 1 << 8, 1 << 7, 1 << 6, 1 << 5, 1 << 3, 1 << 1
RESERVED = (1 << 9) | (1 << 4) | (1 << 2) | (1 << 0)
"""D9 (PIN/SW) and D4 (SIGN/PIB) exist only on the AD9834; D2 and D0 are reserved on both."""


class EmulatedAD9833(SPIChipEmulator):
    """One AD9833 clocked at ``mclk_hz``.

    Attributes
    ----------
    control : int
        The 14-bit control register.
    freq : list[int]
        FREQ0 and FREQ1, 28 bits each.
    phase : list[int]
        PHASE0 and PHASE1, 12 bits each.
    warnings : list[str]
        Notes on writes the chip takes silently but that are almost certainly bugs.
    listeners : list of zero-argument callables
        Called after every change of :attr:`output_hz` or :attr:`waveform`.
    """

    name = "AD9833"
    modes = frozenset({2})
    max_speed_hz = 40_000_000

    def __init__(self, *, mclk_hz: float = 25e6):
        self.mclk_hz = float(mclk_hz)
        self.listeners: list[Callable[[], None]] = []
        self.warnings: list[str] = []
        self._power_on()

    def _power_on(self) -> None:
        self.control = RESET
        self.freq = [0, 0]
        self.phase = [0, 0]
        self._pending_lsb: list[int | None] = [None, None]
        self._halves_since_control: set[int] = set()

    def reset(self) -> None:
        """Back to the power-on state (control = RESET, registers 0, output off)."""
        before = self._output()
        self._power_on()
        self._notify_if_changed(before)

    @property
    def output_hz(self) -> float:
        """The frequency on VOUT: FREQ[FSELECT] * mclk / 2**28, or 0.0 while the output is stopped.

        RESET and SLEEP1 stop the phase accumulator; SLEEP12 powers down the DAC,
        which stops the sine and triangle but not the comparator's square wave.
        A square with DIV2 = 0 is the MSB/2, at half the frequency.
        """
        c = self.control
        if c & (RESET | SLEEP1) or (c & SLEEP12 and not c & OPBITEN):
            return 0.0
        frequency_hz = self.freq[1 if c & FSELECT else 0] * self.mclk_hz / 2**28
        return frequency_hz / 2 if c & OPBITEN and not c & DIV2 else frequency_hz

    @property
    def waveform(self) -> str:
        """``"sine"``, ``"triangle"``, ``"square"`` or ``"off"``."""
        c = self.control
        if c & (RESET | SLEEP1) or (c & SLEEP12 and not c & OPBITEN):
            return "off"
        if c & OPBITEN:
            return "square"
        return "triangle" if c & MODE else "sine"

    def check_frame(self, data: bytes) -> None:
        if not data or len(data) % 2:
            raise EmulatorViolation(f"AD9833: a frame of {len(data)} bytes is not a whole number of 16-bit words")

    def frame(self, data: bytes) -> bytes:
        for i in range(0, len(data), 2):
            before = self._output()
            self._take_word(int.from_bytes(data[i:i + 2], "big"))
            self._notify_if_changed(before)
        return bytes(len(data))

    def _take_word(self, word: int) -> None:
        target = word >> 14
        if target == 0:
            self._write_control(word & 0x3FFF)
        elif target in (1, 2):
            self._write_frequency(target - 1, word & 0x3FFF)
        else:
            self.phase[(word >> 13) & 1] = word & 0x0FFF

    def _write_control(self, bits: int) -> None:
        if bits & RESERVED:
            raise EmulatorViolation(f"AD9833: control word 0x{bits:04X} sets reserved bit(s) 0x{bits & RESERVED:04X} "
                                    "(D9, D4, D2 and D0 must be 0)")
        if bits & OPBITEN and bits & MODE:
            raise EmulatorViolation(f"AD9833: control word 0x{bits:04X} sets OPBITEN with MODE, a reserved combination")
        self.control = bits
        self._halves_since_control.clear()

    def _write_frequency(self, n: int, data: int) -> None:
        if self.control & B28:
            lsb = self._pending_lsb[n]
            if lsb is None:
                self._pending_lsb[n] = data
            else:
                self.freq[n] = (data << 14) | lsb
                self._pending_lsb[n] = None
            return
        msb = bool(self.control & HLB)
        if msb:
            self.freq[n] = (data << 14) | (self.freq[n] & 0x3FFF)
        else:
            self.freq[n] = (self.freq[n] & ~0x3FFF) | data
        if n in self._halves_since_control:
            half = "MSB" if msb else "LSB"
            self.warnings.append(
                f"FREQ{n} was written twice as its 14 {half}s with B28 = 0 (control 0x{self.control:04X}): the "
                f"second write replaced the first instead of completing a 28-bit word, so FREQ{n} is now "
                f"0x{self.freq[n]:07X}. A writer that cleared B28 (control 0x0000 'for sine') and then sent a "
                "two-word frequency gets a wrong frequency; keep B28 set in every control word.")
        self._halves_since_control.add(n)

    def _output(self) -> tuple[float, str]:
        return self.output_hz, self.waveform

    def _notify_if_changed(self, before: tuple[float, str]) -> None:
        if self._output() != before:
            notify(self.listeners)
