"""AD7606 8-channel simultaneous-sampling 16-bit ADCs, many sharing CONVST, BUSY, RESET and RANGE.

Facts used, from the AD7606/AD7606-6/AD7606-4 data sheet (Rev. C) unless noted:

- A rising edge on CONVST A/B (tied together) samples all eight inputs at once;
  BUSY is high while converting and its falling edge loads the output
  registers, so a read before it falls returns the previous conversion.
  Conversion time grows with the oversampling ratio set on OS[2:0]; the
  maximum t_CONV of Table 3 is used (4.15 us at no oversampling, 315 us at 64;
  the AD7607 data sheet's Figure 51 shows 4, 19 and 39 us at 1, 4 and 8).
- The part must be reset after power-up: a RESET pulse (high at least 50 ns;
  the Linux driver gives 100 ns) before the first conversion.
- RANGE high selects +/-10 V, low +/-5 V, for all channels (Linux binding
  ``adi,ad7606.yaml``); codes are 16-bit two's complement, full scale / 32768 per
  LSB (the Linux driver's scales 5000/32768 and 10000/32768 mV).
- Serial read-out (PAR/SER/BYTE SEL high): the CS falling edge puts the MSB of
  V1 on DOUTA and SCLK rising edges clock out the rest, V1 to V8 in order,
  16 SCLKs each (Rev. C p. 28). So SCLK must idle high and be sampled on its
  falling edge: SPI mode 2 (the Linux binding's example also sets ``spi-cpol``).
  The data sheet's SCLK limit falls with the VDRIVE supply; 17 MHz is taken
  for 3.3 V logic [recall: verify against Table 3 before relying on more].

All converters of the front end share CONVST, RESET and RANGE, and their BUSY
outputs are ORed onto one GPIO; each is read through its own output of a
:class:`~appliance.drivers.decoder.ChipSelectDecoder`. GPIO levels the next
step needs (CONVST back low, a new RANGE) wait in a pending set and ride along
with the next decoder address call, so a step costs CONVST, BUSY, and one
address call plus one transfer per converter read.
"""

from __future__ import annotations

from collections.abc import Iterable

from appliance.drivers.bus import FALLING, Clock, GPIOLines, LineRequest
from appliance.drivers.decoder import ChipSelectDecoder
from appliance.errors import ChipNotResponding

CHANNELS = 8
FRAME_BYTES = 2 * CHANNELS
FULL_SCALES_V = (10.0, 5.0)
"""Input range by RANGE level: high (1) +/-10 V, low (0) +/-5 V."""
CONVERSION_S = {1: 4.15e-6, 2: 9.1e-6, 4: 18.8e-6, 8: 39e-6, 16: 78e-6, 32: 158e-6, 64: 315e-6}
"""Maximum conversion time (BUSY high) by oversampling ratio (Table 3)."""
BUSY_TIMEOUT_S = 0.01
"""How long past the conversion time BUSY may stay high before the converters count as not responding."""


def codes_of(frame: bytes) -> tuple[int, ...]:
    """The signed codes of V1..V8 in one 16-byte read-out frame (MSB first)."""
    if len(frame) != FRAME_BYTES:
        raise ValueError(f"an AD7606 frame is {FRAME_BYTES} bytes (8 channels x 16 bits), got {len(frame)}")
    return tuple(int.from_bytes(frame[i:i + 2], "big", signed=True) for i in range(0, FRAME_BYTES, 2))


class AD7606Array:
    """``n_chips`` AD7606s: shared control lines on ``gpio``, read-out through ``decoder`` (chip k on output k)."""

    SPI_MODE = 2
    MAX_SPEED_HZ = 17_000_000

    def __init__(self, gpio: GPIOLines, clock: Clock, decoder: ChipSelectDecoder, *, n_chips: int, convst: str,
                 busy: str, reset: str, range_line: str, oversampling: int = 1):
        if oversampling not in CONVERSION_S:
            raise ValueError(f"AD7606 oversampling ratio {oversampling!r} is not one of {tuple(CONVERSION_S)}")
        if not 1 <= n_chips <= decoder.outputs:
            raise ValueError(f"{n_chips} AD7606s do not fit the decoder's {decoder.outputs} outputs")
        missing = [name for name in (convst, busy, reset, range_line) if name not in gpio.names]
        if missing:
            raise ValueError(f"AD7606: GPIO line {missing[0]} was not requested (lines: {', '.join(gpio.names)})")
        self.gpio, self.clock, self.decoder, self.n_chips = gpio, clock, decoder, n_chips
        self.convst, self.busy, self.reset_line, self.range_line = convst, busy, reset, range_line
        self.oversampling = oversampling
        self._range_level = 1                        # requested: +/-10 V, the least sensitive
        self._written = {convst: 0, reset: 0, range_line: 1}   # as :meth:`line_request` leaves them

    @staticmethod
    def line_request(*, convst: str, busy: str, reset: str, range_line: str,
                     address_lines: Iterable[str]) -> LineRequest:
        """CONVST, RESET and the address low, RANGE high (+/-10 V: nothing can clip at start), BUSY's falling edge."""
        outputs = {convst: 0, reset: 0, range_line: 1, **dict.fromkeys(address_lines, 0)}
        return LineRequest(outputs=outputs, inputs={busy: FALLING})

    @property
    def conversion_s(self) -> float:
        return CONVERSION_S[self.oversampling]

    @property
    def full_scale_v(self) -> float:
        """The input range the next conversion uses, volts (+/- this)."""
        return FULL_SCALES_V[0] if self._range_level else FULL_SCALES_V[1]

    def reset(self) -> None:
        """The RESET pulse the data sheet asks for after power-up (two calls: it lasts one call, 50 us)."""
        self.gpio.set_values({self.reset_line: 1})
        self.gpio.set_values({self.reset_line: 0})
        self._written[self.reset_line] = 0

    def set_range(self, full_scale_v: float) -> None:
        """Choose +/-10 V or +/-5 V for the next conversion (the line changes with the next GPIO call)."""
        if full_scale_v not in FULL_SCALES_V:
            raise ValueError(f"AD7606 range {full_scale_v!r} V is not one of {FULL_SCALES_V}")
        self._range_level = int(full_scale_v == FULL_SCALES_V[0])

    def convert(self) -> None:
        """Sample every channel of every converter now and wait until BUSY falls.

        Pending levels go out first in a call of their own, so RANGE never changes
        together with the CONVST edge and CONVST has been low before it rises.
        """
        self._write(self._pending())
        self.gpio.set_values({self.convst: 1})
        self._written[self.convst] = 1
        timeout = self.conversion_s + BUSY_TIMEOUT_S
        if not self.gpio.wait_edge(self.busy, timeout):
            raise ChipNotResponding(f"AD7606: BUSY on {self.busy} did not fall within {timeout * 1e3:.1f} ms of "
                                    f"CONVST on {self.convst}")

    def read(self, chip: int) -> tuple[int, ...]:
        """The eight codes of ``chip``'s last conversion."""
        if not 0 <= chip < self.n_chips:
            raise ValueError(f"AD7606 {chip} does not exist (0..{self.n_chips - 1})")
        if self.decoder.selected != chip:
            pending = self._pending()
            self.decoder.select(chip, also=pending)
            self._written.update(pending)
        return codes_of(self.decoder.transfer(chip, bytes(FRAME_BYTES)))

    def read_many(self, chips: Iterable[int]) -> dict[int, tuple[int, ...]]:
        """Codes of several converters, the one already addressed first (it needs no address call)."""
        chips = sorted(set(chips))
        if self.decoder.selected in chips:
            chips.remove(self.decoder.selected)
            chips.insert(0, self.decoder.selected)
        return {chip: self.read(chip) for chip in chips}

    @staticmethod
    def volts(code: int, full_scale_v: float) -> float:
        """A code at a range, volts at the converter's input."""
        return code * full_scale_v / 32768

    def forget(self) -> None:
        """After a failed call the lines' state is unknown: send the address and the levels again."""
        self.decoder.forget()
        self._written.clear()

    def _pending(self) -> dict[str, int]:
        """Levels the next conversion needs that the lines do not have yet: CONVST low, the RANGE asked for."""
        wanted = {self.convst: 0, self.range_line: self._range_level}
        return {name: level for name, level in wanted.items() if self._written.get(name) != level}

    def _write(self, values: dict[str, int]) -> None:
        if values:
            self.gpio.set_values(values)
            self._written.update(values)
