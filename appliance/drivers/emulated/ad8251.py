"""AD8251 emulator: latches the gain from A1/A0 on each falling edge of /WR.

It watches the three lines of a :class:`GPIOBank`. Only a high-to-low /WR edge
latches (low-to-low, low-to-high and high-to-high leave the gain alone), as the
datasheet's latched mode specifies; the power-up gain is 1. An address line
that changes together with the /WR falling edge (in the same ``set_values``
call, or at the same simulated instant with no bus call between) has no setup
time, so the latched gain would be undefined on the real chip: that is an
:class:`EmulatorViolation`.
"""

from __future__ import annotations

from collections.abc import Callable

from appliance.drivers.emulated.buses import EmulatorViolation, GPIOBank, notify

GAINS = (1, 2, 4, 8)


class EmulatedAD8251:
    """An AD8251 wired to lines ``a0``, ``a1`` and ``wr`` of ``bank``.

    Attributes
    ----------
    latches : list[tuple[float, int]]
        (time in s, gain) of every latching edge, kept across :meth:`reset`.
    listeners : list of zero-argument callables
        Called after every change of :attr:`gain`.
    """

    name = "AD8251"

    def __init__(self, bank: GPIOBank, *, a0: str, a1: str, wr: str):
        self.bank = bank
        self.a0, self.a1, self.wr = a0, a1, wr
        self.listeners: list[Callable[[], None]] = []
        self.latches: list[tuple[float, int]] = []
        self._gain = 1
        self._changed_at: dict[str, tuple[float, int]] = {}
        self._seen = {name: bank.driven.get(name, 0) for name in (a0, a1)}
        def watcher(name: str) -> Callable[[int, int], None]:
            return lambda old, new: self._address_changed(name, new)

        for name in (a0, a1):
            bank.watch(name, watcher(name))
        bank.watch(wr, self._wr_changed)

    @property
    def gain(self) -> int:
        """The gain now latched."""
        return self._gain

    def reset(self) -> None:
        """Power-up: gain 1."""
        self._set_gain(1)

    def _instant(self) -> tuple[float, int]:
        """When, in bus calls: the time and the log length (each ``set_values`` logs before it drives)."""
        return self.bank.clock.monotonic(), len(self.bank.log)

    def _address_changed(self, name: str, level: int) -> None:
        self._seen[name] = level
        self._changed_at[name] = self._instant()

    def _wr_changed(self, old: int, new: int) -> None:
        if not (old == 1 and new == 0):
            return
        instant = self._instant()
        for name in (self.a0, self.a1):
            if self._changed_at.get(name) == instant or self._seen[name] != self.bank.driven.get(name, 0):
                raise EmulatorViolation(f"AD8251: address line {name} changed together with the /WR falling edge "
                                        "(no setup time); set A1/A0 first, then drop /WR in a separate call")
        gain = GAINS[2 * self.bank.driven.get(self.a1, 0) + self.bank.driven.get(self.a0, 0)]
        self.latches.append((instant[0], gain))
        self._set_gain(gain)

    def _set_gain(self, gain: int) -> None:
        changed = gain != self._gain
        self._gain = gain
        if changed:
            notify(self.listeners)
