"""Electrode contact check: the two-electrode impedance of each neighbouring pair at a small current.

Driving and measuring on the same pair gives the impedance between the two
electrodes through the mat, contact impedances included. An electrode that lost
contact (a broken lead, a dry or lifted pad) makes every pair it belongs to read
high or drives the current source to its rail (over range at the least sensitive
range). Pairs go round the numbering (1-2, 2-3, ..., n-1), so each electrode is in
two pairs; an electrode is open when every pair it belongs to is over the limit,
which keeps one bad electrode from condemning its good neighbours. The parallel
front end checks disjoint pairs along the rows instead and tells a high pair's
open electrode by the channels beside it (:func:`check_contacts_parallel`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import cast

import numpy as np

from appliance.drivers.bus import with_retries
from appliance.drivers.frontend import OVER_RANGE, FrontEnd
from appliance.drivers.frontend_parallel import ParallelFrontEnd


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


def check_contacts(front_end: FrontEnd | ParallelFrontEnd, n_electrodes: int, *, retries: int = 3) -> ContactReport:
    """Measure every neighbouring pair at the contact-test current; the excitation is off afterwards."""
    if getattr(front_end, "parallel", False):
        return check_contacts_parallel(front_end, retries=retries)
    front_end = cast(FrontEnd, front_end)
    pairs = contact_pairs(n_electrodes)
    impedance = np.empty(len(pairs))
    front_end.start_excitation()
    try:
        front_end.contact_current()
        current = front_end.drive_current_a()
        for k, pair in enumerate(pairs):
            # with_retries calls the action before the loop moves on, so it sees this pair.
            measured = with_retries(lambda: front_end.measure(pair, pair), attempts=retries,  # noqa: B023
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


def parallel_contact_pairs(rows: int, cols: int) -> tuple[tuple[int, int], ...]:
    """Disjoint pairs along each row, (1, 2), (3, 4), ...; an odd last electrode is paired with its left neighbour."""
    pairs = []
    for r in range(rows):
        first = r * cols + 1
        pairs += [(first + c, first + c + 1) for c in range(0, cols - 1, 2)]
        if cols % 2:
            pairs.append((first + cols - 2, first + cols - 1))
    return tuple(pairs)


def check_contacts_parallel(front_end, *, retries: int = 3) -> ContactReport:
    """The parallel front end's check: each pair of :func:`parallel_contact_pairs` driven at the test current.

    The pair's own channel gives its two-electrode impedance. The channels just
    outside it share one electrode with it and carry that electrode's own drop
    (contact and spreading, about half the pair's), which tells which of a high
    pair's electrodes is open: one over half the limit is. If neither is, the
    blame goes to an electrode with no channel outside it (at the grid's edge),
    or to both.
    """
    grid, cmap = front_end.profile.grid, front_end.cmap
    pairs = parallel_contact_pairs(grid.rows, grid.cols)
    limit = front_end.profile.contact.limit_ohm
    impedance = np.empty(len(pairs))
    single: dict[int, float] = {}
    front_end.start_excitation()
    try:
        front_end.contact_current()
        current = front_end.drive_current_a()
        for k, (a, b) in enumerate(pairs):
            col = (a - 1) % grid.cols
            wanted = [(a, b)] + ([(a - 1, a)] if col > 0 else []) + ([(b, b + 1)] if col + 2 < grid.cols else [])
            channels = [cmap.channel_of(p, q)[0] for p, q in wanted]
            then = pairs[k + 1] if k + 1 < len(pairs) else None
            # with_retries calls the action before the loop moves on, so it sees this pair's values.
            sample = with_retries(lambda: front_end.step((a, b), channels, 0, then=then),  # noqa: B023
                                  attempts=retries,
                                  what=f"contact check of electrodes {a}-{b}",
                                  on_retry=lambda *_: front_end.forget_routing())
            ohm = np.where(sample.fraction > OVER_RANGE, math.inf, np.abs(sample.volts) / current)
            impedance[k] = ohm[0]
            for (_, q), z in zip(wanted[1:], ohm[1:]):
                single[a if q == a else b] = float(z)
    finally:
        front_end.stop_excitation()
    open_electrodes = set()
    for (a, b), z in zip(pairs, impedance):
        if z <= limit:
            continue
        high = {e for e in (a, b) if single.get(e, 0.0) > limit / 2}
        untold = {e for e in (a, b) if e not in single}
        open_electrodes |= high or untold or {a, b}
    return ContactReport(pairs, impedance, limit, frozenset(open_electrodes))
