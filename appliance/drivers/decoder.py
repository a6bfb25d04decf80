"""One SPI chip select fanned out to many chips by a decoder (74HC154) on GPIO address lines.

The Raspberry Pi has two or three chip selects per SPI controller; the parallel
front end has 64 ADCs. The controller's CE line enables the decoders (their
active-low G inputs), and GPIO lines give the address, so the chip select of
output ``n`` is low exactly for the SPI frame sent while the address reads
``n``: one GPIO call and one SPI transfer per chip. The address is only written
when it changes, and values for other lines of the same request (a CONVST
falling edge, a RANGE change) can ride along in that one call.

It works on any :class:`~appliance.drivers.bus.Board`: the Linux board gives a
spidev node and gpiod lines, the emulated one fakes both. Address lines are
least significant first.

>>> from appliance.drivers.bus import LineRequest
>>> from appliance.drivers.emulated.buses import BusTiming, EmulatedGPIOLines, GPIOBank
>>> from appliance.drivers.emulated.clock import SimulatedClock
>>> bank = GPIOBank(SimulatedClock(), ["GPIO4", "GPIO5"], [])
>>> lines = EmulatedGPIOLines(bank, LineRequest({"GPIO4": 0, "GPIO5": 0}, {}), "decoder", BusTiming())
>>> ChipSelectDecoder(None, lines, ("GPIO4", "GPIO5")).address_values(2)
{'GPIO4': 0, 'GPIO5': 1}
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from appliance.drivers.bus import GPIOLines, SPIDevice


class ChipSelectDecoder:
    """``spi`` (the decoders' enable) reaching ``2 ** len(address_lines)`` chips through ``gpio``'s address lines."""

    def __init__(self, spi: SPIDevice, gpio: GPIOLines, address_lines: Sequence[str]):
        missing = [name for name in address_lines if name not in gpio.names]
        if missing:
            raise ValueError(f"decoder address line {missing[0]} was not requested (lines: {', '.join(gpio.names)})")
        self.spi, self.gpio, self.address_lines = spi, gpio, tuple(address_lines)
        self.outputs = 2 ** len(self.address_lines)
        self._address: int | None = None

    def address_values(self, index: int) -> dict[str, int]:
        """The level of each address line that selects output ``index``."""
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < self.outputs:
            raise ValueError(f"decoder output {index!r} is out of range 0..{self.outputs - 1}")
        return {name: (index >> bit) & 1 for bit, name in enumerate(self.address_lines)}

    @property
    def selected(self) -> int | None:
        """The output the address lines select now (None until first set, or after :meth:`forget`)."""
        return self._address

    def select(self, index: int, also: Mapping[str, int] | None = None) -> None:
        """Put output ``index`` on the address lines, with ``also`` in the same call; nothing if neither changes."""
        values = self.address_values(index) if index != self._address else {}
        values.update(also or {})
        if values:
            self.gpio.set_values(values)
        self._address = index

    def transfer(self, index: int, data: bytes, also: Mapping[str, int] | None = None) -> bytes:
        """One SPI frame to the chip on output ``index``."""
        self.select(index, also)
        return self.spi.transfer(data)

    def forget(self) -> None:
        """After a failed call the lines' state is unknown: write the address again next time."""
        self._address = None
