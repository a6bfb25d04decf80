"""The notification service: the alarm changes of a hospital's wards paged to a messaging gateway (the nurses'
phones and pagers), and what became of each page recorded on the engine.

A service (a ``[[notifier]]`` of the hospital description) reads each of its wards' streams through its own
durable consumer, named as its engine user (``notify-<name>``), apart from the stations' and the history's. For
each alarm event of its priorities (turn and episode events are not paged), in this order:

1. its journal (an :class:`~appliance.ward.applied.AppliedJournal` on disk, which the caller opens) is asked
   whether the event was dealt with before: one given again after that is not POSTed again;
2. the event is POSTed as JSON to the gateway with the header ``Idempotency-Key: <bed>:<seq>`` (the engine's
   message id), so the gateway drops the second copy of the one page a crash can repeat, the one in flight;
3. a 2xx answer is journalled as paged; a 400, 404, 413 or 422 (a page the gateway will never take) as refused,
   with its status;
4. that record goes to the ward's confirmation stream as ``hospital.<ward>.<bed>.notified.<seq>.<name>`` and is
   acknowledged there by a quorum, and only then is the event acknowledged to the ward's stream.

Any other answer, a timeout or a refused connection leaves the event unacknowledged: the stream gives it again
after the consumer's acknowledgement wait, and the service tries again at that pace for the first
``RETRY_STEADY_S`` of an outage (most are a gateway's restart or failover), then waits longer after each failure,
up to ``RETRY_MAX_S``. While the gateway takes no pages, :meth:`NotificationService.conditions` says so (a technical
alarm, as the ward link's), and the log says it once when the outage begins and once when it ends. After an
outage pages may reach the gateway out of order: each carries its bed's ``seq`` and ``time_s``.

A gateway that died at night must not wait for the next alarm to be found out: while no page has been tried for
``PROBE_EVERY_S`` the service asks the gateway whether it is there (:func:`probe_gateway`: its ``probe_url``, which
must answer 2xx, or else a HEAD of the page address, which any answer below 500 passes) and counts a probe that
fails as a page that failed, until a probe or a page goes through.

The nurses see it too: the service tells each of its wards' stations whether pages go out (:func:`paging_status`
on ``hospital.<ward>.paging.status.<name>``), at once when that changes and again every ``STATUS_EVERY_S``. A
plain message, repeated, rather than a last value kept in a stream: a station must notice a service that stopped
saying anything (dead, or cut off from the engine), which only a message expected at a known pace shows, and
once that pace is there it also tells a station started afresh within one period; a stream would add a quorum
write every period and still need the pace.
"""

from __future__ import annotations

import asyncio
import contextlib
import http.client
import json
import logging
import sqlite3
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from typing import Protocol

import nats.errors
import nats.js.errors
from nats.aio.client import Client

from appliance.hospital.description import Notifier
from appliance.hospital.engine import RETRYABLE, Delivery, WardReader
from appliance.hospital.nodeconfig import notifier_user
from appliance.hospital.subjects import confirms_stream_name, message_id, notified_subject, paging_status_subject

log = logging.getLogger(__name__)

IDEMPOTENCY_KEY = "Idempotency-Key"
REFUSED_FOR_GOOD = frozenset({400, 404, 413, 422})
"""Answers no retry would change: the gateway refuses the page's content, or has no such address."""
PAGED, REFUSED = "paged", "refused"
POST_TIMEOUT_S = 5.0
"""How long one POST waits for the gateway's answer before the page counts as not taken."""
RECORD_TIMEOUT_S = 2.0
"""How long the service waits for the confirmation stream's acknowledgement before it leaves the event to be
given again."""
RETRY_FIRST_S = 1.0
RETRY_STEADY_S = 60.0
"""How long into an outage the gateway is still tried at the first pace, so a short one holds no page long."""
RETRY_MAX_S = 30.0
FETCH_BATCH = 20
"""Events fetched at once: few, because they are paged one after the other and each must be acknowledged
within the consumer's acknowledgement wait or it is given again (and then found in the journal)."""
STREAM_WAIT_S = 10.0
PROBE_EVERY_S = 60.0
"""While no page is tried, how often the gateway is probed: an outage shows within a minute or two of its start."""
STATUS_EVERY_S = 5.0
"""How often the service says whether pages go out, when nothing changed: a station that hears nothing for a few
of these shows the service's state as unknown."""


class GatewayUnavailable(Exception):
    """The gateway did not take a page this time: no answer, or one that a later try may change."""


class PageJournal(Protocol):
    """What the service has dealt with, on disk: ``take`` journals an event's record, ``event`` finds it."""

    def take(self, delivery: Delivery) -> bool:
        """Journal ``delivery`` (its event is the record); False when its bed's number was taken before."""

    def event(self, bed_id: str, seq: int) -> dict | None:
        """The record journalled for bed ``bed_id``'s event ``seq``, or None."""


class _NoRedirects(urllib.request.HTTPRedirectHandler):
    """A redirect is not followed (urllib would send a POST on as a GET without its body): it is an answer that
    a later try may change, once the gateway's address is corrected."""

    def redirect_request(self, req, fp, code, msg, headers, newurl):
        return None


_OPENER = urllib.request.build_opener(_NoRedirects)


def post_page(url: str, key: str, body: bytes, timeout_s: float) -> int:
    """POST JSON ``body`` to ``url`` with idempotency key ``key``: the HTTP status the gateway answered, or
    GatewayUnavailable when it did not answer within ``timeout_s``."""
    request = urllib.request.Request(url, data=body, method="POST",
                                     headers={"Content-Type": "application/json", IDEMPOTENCY_KEY: key})
    try:
        with _OPENER.open(request, timeout=timeout_s) as reply:
            return reply.status
    except urllib.error.HTTPError as exc:
        exc.close()
        return exc.code
    except (OSError, http.client.HTTPException) as exc:     # refused, reset, timed out, or not HTTP
        raise GatewayUnavailable(str(getattr(exc, "reason", exc)) or type(exc).__name__) from exc


def probe_gateway(url: str, health: bool, timeout_s: float) -> None:
    """Ask the gateway at ``url`` whether it is there: GET its health address (``health``), which must answer 2xx, or
    HEAD its page address, which must answer below 500 (a 405 still shows a server that answers); raises
    GatewayUnavailable naming what it answered, or that it did not."""
    request = urllib.request.Request(url, method="GET" if health else "HEAD")
    try:
        with _OPENER.open(request, timeout=timeout_s) as reply:
            status = reply.status
    except urllib.error.HTTPError as exc:
        exc.close()
        status = exc.code
    except (OSError, http.client.HTTPException) as exc:
        raise GatewayUnavailable(f"no answer to a probe: {getattr(exc, 'reason', exc) or type(exc).__name__}") from exc
    if status >= 500 or (health and not 200 <= status < 300):
        raise GatewayUnavailable(f"HTTP {status} to a probe")


def paging_status(notifier: str, delivering: bool, since: float, reason: str, every_s: float) -> bytes:
    """What a station hears of notification service ``notifier``: whether its gateway takes pages, since when
    (``time.time()``), why not (``reason``, empty while it does), and the pace it says this at."""
    return json.dumps({"notifier": notifier, "delivering": delivering, "since": since, "reason": reason,
                       "every_s": every_s}).encode()


class NotificationService:
    """``notifier``'s service on ``connection`` (logged in as its user), keeping what it did in ``journal``;
    ``post`` sends one page (:func:`post_page`), ``probe`` asks whether the gateway is there (:func:`probe_gateway`)
    after ``probe_every_s`` without a page; its wards' stations hear whether pages go out every ``status_every_s``.
    Counters: ``paged`` and ``refused`` (each event once), ``repeats`` (events given again that had been dealt with),
    ``failures`` (tries the gateway did not take)."""

    def __init__(self, connection: Client, notifier: Notifier, journal: PageJournal, *,
                 post: Callable[[str, str, bytes, float], int] = post_page, timeout_s: float = POST_TIMEOUT_S,
                 probe: Callable[[str, bool, float], None] = probe_gateway, probe_every_s: float = PROBE_EVERY_S,
                 status_every_s: float = STATUS_EVERY_S):
        self.connection, self.notifier, self.journal = connection, notifier, journal
        self.user = notifier_user(notifier.name)
        self.js = connection.jetstream()
        self.post, self.timeout_s, self.status_every_s = post, timeout_s, status_every_s
        self.probe, self.probe_every_s = probe, probe_every_s
        self.paged = self.refused = self.repeats = self.failures = 0
        self._down_since: float | None = None         # time.monotonic() of the first try the gateway did not take
        self._down_reason = ""
        self._down_by_probe = False                   # no page failed: only a probe says the gateway is not there
        self._last_try = time.monotonic()             # of a page; the gateway is probed after probe_every_s without
        self._state_since = time.time()               # when pages last began or stopped going out, for the nurses
        self._state_changed = asyncio.Event()
        self._retry_s = RETRY_FIRST_S
        self._stopping = asyncio.Event()

    def conditions(self) -> dict[str, str]:
        """The technical alarm the service earns now: its gateway not taking pages."""
        if self._down_since is None:
            return {}
        down_s = time.monotonic() - self._down_since
        what = "answered no probe" if self._down_by_probe else "taken no page"
        return {f"technical:{self.user}": f"the {self.notifier.name} gateway has {what} for {down_s:.0f} s "
                                          f"({self._down_reason}): alarm changes are not reaching "
                                          f"{self.notifier.name}"}

    async def run(self) -> None:
        """Page every ward's alarm changes until :meth:`stop`; a ward's reader that fails raises its error here."""
        readers = [asyncio.create_task(self._serve(ward), name=f"{self.user} {ward}") for ward in self.notifier.wards]
        readers.append(asyncio.create_task(self._tell_stations(), name=f"{self.user} status"))
        readers.append(asyncio.create_task(self._watch_gateway(), name=f"{self.user} probe"))
        stopping = asyncio.create_task(self._stopping.wait())
        try:
            done, _ = await asyncio.wait([stopping, *readers], return_when=asyncio.FIRST_COMPLETED)
            for task in done - {stopping}:
                task.result()
        finally:
            for task in (stopping, *readers):
                task.cancel()
            await asyncio.gather(stopping, *readers, return_exceptions=True)

    def stop(self) -> None:
        """End :meth:`run`: what was not acknowledged is given again at the next start."""
        self._stopping.set()

    def pages(self, delivery: Delivery) -> bool:
        """Whether ``delivery`` is paged: an alarm change of one of the service's priorities."""
        return delivery.kind == "alarm" and delivery.event.get("priority") in self.notifier.priorities

    async def _serve(self, ward: str) -> None:
        reader = WardReader(self.connection, ward, self.user)

        async def handle(delivery: Delivery, fresh: bool) -> None:
            await self._handle(ward, delivery)

        while True:
            try:
                if reader.subscription is None:
                    await reader.open()
                await reader.read(FETCH_BATCH, handle=handle)
            except GatewayUnavailable:                  # given again by the stream; past a minute, less often
                await asyncio.sleep(self._retry_s)
                if self._down_since is not None and time.monotonic() - self._down_since > RETRY_STEADY_S:
                    self._retry_s = min(2 * self._retry_s, RETRY_MAX_S)
            except nats.js.errors.NotFoundError:
                log.warning("%s: ward %s has no stream yet (appliance hospital streams makes it)", self.user, ward)
                await asyncio.sleep(STREAM_WAIT_S)
            except RETRYABLE as exc:
                log.warning("%s: ward %s's stream is not readable now: %r", self.user, ward, exc)
                await asyncio.sleep(RETRY_FIRST_S)
            except sqlite3.Error as exc:                # what was not journalled is not acknowledged: given again
                log.error("%s: the journal of pages refuses writes: %s", self.user, exc)
                await asyncio.sleep(RETRY_MAX_S)

    async def _tell_stations(self) -> None:
        """Say to every ward whether pages go out: at once when that changes, else every ``status_every_s``. A
        status the engine does not take now is not kept: the next one says the same, newer."""
        while True:
            self._state_changed.clear()
            status = paging_status(self.notifier.name, self._down_since is None, self._state_since,
                                   self._down_reason if self._down_since is not None else "", self.status_every_s)
            for ward in self.notifier.wards:
                try:
                    await self.connection.publish(paging_status_subject(ward, self.notifier.name), status)
                except nats.errors.Error as exc:
                    log.debug("%s: status to %s not sent: %r", self.user, ward, exc)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._state_changed.wait(), self.status_every_s)

    async def _watch_gateway(self) -> None:
        """Probe the gateway whenever no page was tried for ``probe_every_s``; a failed probe is an outage until a
        probe or a page goes through (an outage a page found ends only with a page taken)."""
        url, health = (self.notifier.probe_url, True) if self.notifier.probe_url else (self.notifier.url, False)
        while True:
            idle_s = time.monotonic() - self._last_try
            if idle_s < self.probe_every_s:
                await asyncio.sleep(self.probe_every_s - idle_s)
                continue
            if self._down_since is None or self._down_by_probe:
                started, failure = time.monotonic(), None
                try:
                    await asyncio.to_thread(self.probe, url, health, self.timeout_s)
                except GatewayUnavailable as exc:
                    failure = str(exc)
                if self._last_try < started:            # a page tried meanwhile tells more than the probe
                    if failure is None:
                        self._gateway_up()
                    else:
                        self._gateway_down(failure, by_probe=True)
            await asyncio.sleep(self.probe_every_s)

    async def _handle(self, ward: str, delivery: Delivery) -> None:
        """Page ``delivery`` unless the journal has it, journal the outcome, record it on a quorum; raises when
        the gateway did not take it or the engine could not keep the record, so the event is given again."""
        if not self.pages(delivery):
            return
        record = await asyncio.to_thread(self.journal.event, delivery.bed, delivery.seq)
        if record is None:
            status = await self._page(ward, delivery)
            record = {"bed_id": delivery.bed, "seq": delivery.seq, "notifier": self.notifier.name,
                      "outcome": PAGED if status < 300 else REFUSED, "status": status,
                      "alarm_id": delivery.event.get("alarm_id"), "kind": delivery.event.get("kind"),
                      "notified_at": time.time()}
            await asyncio.to_thread(self.journal.take, Delivery(delivery.bed, delivery.seq, delivery.kind, record))
            if record["outcome"] == PAGED:
                self.paged += 1
            else:
                self.refused += 1
        else:
            self.repeats += 1
        await self.js.publish(notified_subject(ward, delivery.bed, delivery.seq, self.notifier.name),
                              json.dumps(record).encode(), timeout=RECORD_TIMEOUT_S, stream=confirms_stream_name(ward))

    async def _page(self, ward: str, delivery: Delivery) -> int:
        """POST the event: the gateway's status when it took the page or refused it for good, else
        GatewayUnavailable."""
        body = json.dumps({**delivery.event, "ward": ward}, separators=(",", ":")).encode()
        self._last_try = time.monotonic()
        try:
            status = await asyncio.to_thread(self.post, self.notifier.url, message_id(delivery.bed, delivery.seq),
                                             body, self.timeout_s)
            if not (200 <= status < 300 or status in REFUSED_FOR_GOOD):
                raise GatewayUnavailable(f"HTTP {status}")
        except GatewayUnavailable as exc:
            self.failures += 1
            self._gateway_down(str(exc))
            raise
        self._gateway_up()
        if status in REFUSED_FOR_GOOD:
            log.error("%s: the gateway refused %s's alarm change %d for good (HTTP %d): recorded as refused",
                      self.user, delivery.bed, delivery.seq, status)
        return status

    def _gateway_down(self, reason: str, by_probe: bool = False) -> None:
        changed = reason != self._down_reason
        self._down_reason, self._down_by_probe = reason, by_probe
        if self._down_since is None:
            self._down_since, self._state_since = time.monotonic(), time.time()
            log.error("%s: the gateway %s takes no pages (%s): alarm changes are held and tried again until it "
                      "does", self.user, self.notifier.url, reason)
            changed = True
        if changed:
            self._state_changed.set()

    def _gateway_up(self) -> None:
        self._retry_s = RETRY_FIRST_S
        if self._down_since is not None:
            log.warning("%s: the gateway takes pages again after %.0f s", self.user,
                        time.monotonic() - self._down_since)
            self._down_since, self._down_reason, self._down_by_probe = None, "", False
            self._state_since = time.time()
            self._state_changed.set()
