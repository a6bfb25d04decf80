"""Electrode contact check: the two-electrode impedance of each neighbouring pair at a small current.

Driving and measuring on the same pair gives the impedance between the two
electrodes through the mat, contact impedances included. An electrode that lost
contact (a broken lead, a dry or lifted pad) makes every pair it belongs to read
high or drives the current source to its rail (over range at the least sensitive
range). Pairs go round the numbering (1-2, 2-3, ..., n-1), so each electrode is in
two pairs; an electrode is open when every pair it belongs to is over the limit,
which keeps one bad electrode from condemning its good neighbours.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from appliance.drivers.bus import with_retries
from appliance.drivers.frontend import FrontEnd


@dataclass(frozen=True)
class ContactReport:
    """Impedance of each checked pair (ohm, inf when over range) and the electrodes judged open."""

    pairs: tuple[tuple[int, int], ...]
    impedance_ohm: np.ndarray
    limit_ohm: float
    open_electrodes: frozenset[int]

    def table(self) -> str:
        """A fixed-width table for the operator: pair, impedance, verdict."""
        lines = [f"{'pair':>7}  {'impedance':>12}  status"]
        for (a, b), z in zip(self.pairs, self.impedance_ohm):
            shown = "over range" if math.isinf(z) else f"{z:.1f} ohm"
            lines.append(f"{a:>3}-{b:<3}  {shown:>12}  {'HIGH' if z > self.limit_ohm else 'ok'}")
        verdict = ", ".join(map(str, sorted(self.open_electrodes))) or "none"
        lines.append(f"open electrodes: {verdict}")
        return "\n".join(lines)


def contact_pairs(n_electrodes: int) -> tuple[tuple[int, int], ...]:
    """Neighbouring pairs round the numbering: (1, 2), (2, 3), ..., (n, 1)."""
    if n_electrodes < 2:
        raise ValueError("a contact check needs at least two electrodes")
    if n_electrodes == 2:
        return ((1, 2),)
    return tuple((e, e % n_electrodes + 1) for e in range(1, n_electrodes + 1))


def check_contacts(front_end: FrontEnd, n_electrodes: int, *, retries: int = 3) -> ContactReport:
    """Measure every neighbouring pair at the contact-test current; the excitation is off afterwards."""
    pairs = contact_pairs(n_electrodes)
    impedance = np.empty(len(pairs))
    front_end.start_excitation()
    try:
        front_end.contact_current()
        current = front_end.drive_current_a()
        for k, pair in enumerate(pairs):
            measured = with_retries(lambda: front_end.measure(pair, pair), attempts=retries,
                                    what=f"contact check of electrodes {pair[0]}-{pair[1]}",
                                    on_retry=lambda *_: front_end.forget_routing())
            impedance[k] = math.inf if measured.saturated else abs(measured.sample.volts) / current
    finally:
        front_end.stop_excitation()
    limit = front_end.profile.contact.limit_ohm
    high = impedance > limit
    open_electrodes = frozenset(e for e in range(1, n_electrodes + 1)
                                if all(high[k] for k, pair in enumerate(pairs) if e in pair))
    return ContactReport(pairs, impedance, limit, open_electrodes)
