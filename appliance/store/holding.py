"""The monitor's writes to the store, held in memory while the disk refuses them.

A full SD card (or a failing one) must not stop monitoring: alarms are raised,
shown and notified from memory whatever the store does. Each frame's records
go through :class:`HeldWrites`; when a write fails they are kept, in order, and
written with the next frame that can write, after which nothing is held. What
is held is bounded: events and command outcomes are small and kept (up to
``MAX_HELD_EVENTS``), alert states are only ever needed as the newest, and the
down-sampled pressure history (a convenience, not the audit trail) keeps its
newest ``MAX_HELD_MAPS`` maps. ``condition()`` is the technical alarm the
daemon raises meanwhile.
"""

from __future__ import annotations

import errno
import logging
import sqlite3
from collections import deque
from collections.abc import Iterable, Mapping

from appliance.store.database import Store

log = logging.getLogger(__name__)

MAX_HELD_EVENTS = 100_000
MAX_HELD_MAPS = 1440                # a day of the default history (a map a minute), about 3 MB


def storage_failure(exc: BaseException) -> bool:
    """Whether ``exc`` is the disk refusing a write (full, failing, or locked past the timeout), which holding
    the records can outlast, rather than a fault in what was written."""
    return isinstance(exc, (sqlite3.OperationalError, OSError))


def disk_full(exc: BaseException) -> bool:
    return (getattr(exc, "sqlite_errorcode", None) == sqlite3.SQLITE_FULL
            or getattr(exc, "errno", None) == errno.ENOSPC or "disk is full" in str(exc))


class HeldWrites:
    """Frame commits, history maps and states for ``store``, written at once when the disk takes them and held
    in order when it does not."""

    def __init__(self, store: Store, *, max_events: int = MAX_HELD_EVENTS, max_maps: int = MAX_HELD_MAPS):
        self.store = store
        self.max_events = max_events
        self._events: deque = deque()
        self._states: dict[str, dict] = {}
        self._outcomes: list[tuple[int, bool, str]] = []
        self._ward: dict[str, dict] = {}                # the ward's commands applied, by ward id
        self._now_s = 0.0
        self._maps: deque = deque(maxlen=max_maps)
        self._last_held_map_s: float | None = None
        self.dropped_events = self.dropped_maps = 0
        self.failure: str | None = None            # the last write's error while records are held
        self.full = False

    @property
    def held(self) -> int:
        """Records held in memory: events, maps and command outcomes."""
        return len(self._events) + len(self._maps) + len(self._outcomes) + len(self._ward)

    @property
    def held_commands(self) -> set[int]:
        """Commands applied whose outcome is not yet written: they must not be applied again."""
        return {command_id for command_id, _, _ in self._outcomes}

    def held_ward_command(self, ward_id: str) -> dict | None:
        """The ward's command ``ward_id`` if it was applied but is not yet written: it must not be applied again."""
        return self._ward.get(ward_id)

    def condition(self) -> dict[str, str]:
        """The technical alarm while records are held or were lost: ``{"technical:storage": message}``."""
        if self.failure is None:
            return {}
        what = "storage full" if self.full else f"storage failing ({self.failure})"
        lost = f"; {self.dropped_events} event(s) and {self.dropped_maps} map(s) dropped" \
            if self.dropped_events or self.dropped_maps else ""
        return {"technical:storage": f"{what}: records kept in memory ({self.held} held{lost})"}

    def record_map(self, time_s: float, pressure_kpa, regions: Iterable[Mapping] = ()) -> None:
        """The store's ``record_map``, held if the history would keep it and the disk refuses it."""
        if not self._maps and self.failure is None:
            try:
                self.store.record_map(time_s, pressure_kpa, regions)
                return
            except Exception as exc:
                if not storage_failure(exc):
                    raise
                self._failed(exc)
        last = max((t for t in (self.store.last_map_s, self._last_held_map_s) if t is not None), default=None)
        if last is not None and time_s - last < self.store.history_interval_s:
            return
        if len(self._maps) == self._maps.maxlen:
            self.dropped_maps += 1
        self._maps.append((time_s, pressure_kpa, [dict(r) for r in regions]))
        self._last_held_map_s = time_s

    def save_state(self, name: str, state: dict, now_s: float) -> None:
        self.commit_frame(now_s, [], {name: state})

    def commit_frame(self, now_s: float, events: Iterable, states: Mapping[str, dict],
                     commands_done: Iterable[tuple[int, bool, str]] = (),
                     ward_commands: Iterable[Mapping] = ()) -> None:
        """The store's ``commit_frame`` after everything held before it, in order; held too if the disk refuses
        it. Only the newest of each state is needed, so states held are replaced, not queued."""
        self._now_s = now_s
        self._events.extend(events)
        while len(self._events) > self.max_events:
            self._events.popleft()
            self.dropped_events += 1
        self._states.update(states)
        self._outcomes.extend(commands_done)
        self._ward.update((c["ward_id"], dict(c)) for c in ward_commands)
        self.flush()

    def flush(self) -> bool:
        """Write what is held, oldest first; True when nothing is held any more."""
        try:
            while self._maps:
                time_s, pressure, regions = self._maps[0]
                self.store.record_map(time_s, pressure, regions)
                self._maps.popleft()
            if self._events or self._states or self._outcomes or self._ward:
                self.store.commit_frame(self._now_s, list(self._events),
                                        dict(self._states), self._outcomes, self._ward.values())
                self._events.clear()
                self._states.clear()
                self._outcomes = []
                self._ward = {}
        except Exception as exc:
            if not storage_failure(exc):
                raise
            self._failed(exc)
            return False
        if self.failure is not None:
            log.warning("the store takes writes again: the records held in memory are written (%d event(s) and "
                        "%d map(s) had been dropped)", self.dropped_events, self.dropped_maps)
        self.failure, self.full = None, False
        self._last_held_map_s = None
        return True

    def _failed(self, exc: BaseException) -> None:
        if self.failure is None:
            log.error("cannot write to the store %s (%s): records are kept in memory", self.store.path, exc)
        self.failure, self.full = f"{type(exc).__name__}: {exc}", disk_full(exc)
