"""The nurse-call output: one dry-contact relay per alarm priority, closed while that priority needs a nurse.

A hospital's nurse-call system takes a bed's alarms as contact closures on its
bedside inputs (a dry contact: the relay's contacts carry none of the
appliance's own power). The appliance drives each relay's coil from a GPIO
line, through the same :class:`~appliance.drivers.bus.GPIOLines` interface the
front end's drivers use, and sets every line once a frame from the alarm
engine's open alarms:

- ``latched`` (the default): a priority's relay is closed while any alarm of
  that priority is unacknowledged, whether its condition still holds or has
  cleared; an acknowledgement (at the bed, or from the ward station) opens it.
- ``follow``: closed while an alarm of that priority is unacknowledged and its
  condition still holds, so it opens when the condition clears too.

Pausing the audio acknowledges nothing, so it leaves the relays closed.
``active_low`` is for relay boards whose coil is energised by a low line.

A line that cannot be driven (a GPIO fault) must neither stop the monitor nor
pass unnoticed: the error is kept, :meth:`NurseCallRelays.conditions` turns it
into the technical alarm ``technical:nurse-call`` (shown and sounded at the
bed, and sent to the ward station like any alarm), and every frame tries
again until a write succeeds. On close every relay is opened.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from typing import Protocol

from appliance.alerts.alarms import AWAITING_ACK, PRIORITIES, Alarm
from appliance.errors import ApplianceError

log = logging.getLogger(__name__)

MODES = ("latched", "follow")


class OutputLines(Protocol):
    """What the relays need of the board's :class:`~appliance.drivers.bus.GPIOLines` (named here, not imported,
    so that the configuration's checks, which the screen runs too, import no driver)."""

    def set_values(self, values: Mapping[str, int]) -> None: ...


class NurseCallRelays:
    """Drives ``relays`` (priority -> GPIO line name) on ``lines`` as ``mode`` says."""

    def __init__(self, lines: OutputLines, relays: Mapping[str, str], *, mode: str = "latched",
                 active_low: bool = False):
        check(relays, mode)
        self.lines, self.relays, self.mode = lines, dict(relays), mode
        self.closed_level = 0 if active_low else 1
        self.fault: str | None = None
        self.closed: dict[str, bool] = dict.fromkeys(self.relays, False)

    @property
    def open_level(self) -> int:
        """The level of a line whose relay is open: what to request the lines with."""
        return 1 - self.closed_level

    def wanted(self, alarms: Iterable[Alarm]) -> dict[str, bool]:
        """Which relays should be closed for ``alarms`` (the engine's open alarms)."""
        calling = {a.priority for a in alarms if not a.acknowledged
                   and (self.mode == "latched" or a.state != AWAITING_ACK)}
        return {priority: priority in calling for priority in self.relays}

    def show(self, alarms: Iterable[Alarm]) -> None:
        """Set every relay for ``alarms``; a line that cannot be driven is kept as ``fault``, never raised."""
        self._write(self.wanted(alarms))

    def conditions(self) -> dict[str, str]:
        """The technical alarm while a relay cannot be driven."""
        if self.fault is None:
            return {}
        return {"technical:nurse-call": f"the nurse-call relays cannot be set ({self.fault}): the nurse-call "
                                        f"system may not hear this bed's alarms"}

    def close(self) -> None:
        """Open every relay (the board gives the lines back when it closes)."""
        self._write(dict.fromkeys(self.relays, False))

    def _write(self, wanted: dict[str, bool]) -> None:
        values = {self.relays[p]: self.closed_level if closed else self.open_level for p, closed in wanted.items()}
        try:
            self.lines.set_values(values)
        except (OSError, ApplianceError) as exc:
            if self.fault is None:
                log.error("nurse-call relays: cannot set the lines %s: %s", ", ".join(values), exc)
            self.fault = f"{type(exc).__name__}: {exc}"
            return
        if self.fault is not None:
            log.warning("nurse-call relays: the lines can be set again after %s", self.fault)
        self.fault, self.closed = None, wanted


def check(relays: Mapping[str, str], mode: str) -> None:
    """ValueError unless ``relays`` maps priorities to distinct line names and ``mode`` is one of ``MODES``."""
    if not relays:
        raise ValueError(f"nurse-call relays need a line for at least one priority of {', '.join(PRIORITIES)}")
    unknown = sorted(set(relays) - set(PRIORITIES))
    if unknown:
        raise ValueError(f"nurse-call relays are per priority ({', '.join(PRIORITIES)}), got {unknown[0]!r}")
    if len(set(relays.values())) != len(relays):
        raise ValueError(f"each nurse-call relay needs a line of its own, got {dict(relays)}")
    if mode not in MODES:
        raise ValueError(f"nurse-call mode must be one of {', '.join(MODES)}, got {mode!r}")
