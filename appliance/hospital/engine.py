"""Beds and stations on the engine with the native NATS client: a bed's event is confirmed only when the
ward's stream has it on a quorum, and a station applies each bed's sequence number once.

JetStream acknowledges a publish after the stream's leader has replicated it to a majority of its replicas
(each node fsyncing every write, ``sync_interval: always``), and keeps one copy per ``Nats-Msg-Id`` inside the stream's
duplicate window. So a bed resends an event under the same id until it holds an acknowledgement, whatever
node died meanwhile (:meth:`BedPublisher.send`); a station reads the ward's stream through its own durable
consumer, acknowledges each message after applying it, and applies a bed's number only once
(:class:`WardReader`), which covers resends outside the window and redeliveries after a lost
acknowledgement.
"""

from __future__ import annotations

import asyncio
import json
import logging
import ssl
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import nats
import nats.errors
import nats.js.errors
from nats.aio.client import Client
from nats.js import JetStreamContext, api

from appliance.hospital.description import Hospital, Ward
from appliance.hospital.nodeconfig import DUPLICATE_WINDOW_S
from appliance.hospital.subjects import (CONFIRMED, MSG_ID, bed_subject, confirms_stream_name, inbox_prefix,
                                         notified_subject, parse_message_id, stream_name, stream_subjects)
from appliance.hospital.tls import client_context, tls_urls

log = logging.getLogger(__name__)

RECONNECT_WAIT_S = 0.25
PUBLISH_TIMEOUT_S = 2.0
"""How long one publish waits for the stream's acknowledgement before it is sent again: a leader's election
after a node's death takes a few seconds, during which publishes time out."""
ACK_WAIT_S = 5.0
"""How long the ward's stream waits for a station's acknowledgement before it gives the message again: a
station that could not confirm (no quorum) takes it up again this soon after the engine is whole."""
CONFIRMS_KEPT_S = 7 * 86400.0
"""How long a confirmation stays in the engine: far longer than a bed resends an event (it resends every minute
at most), so a bed back after a long cut still finds the confirmations it missed."""
RETRYABLE = (nats.errors.TimeoutError, nats.errors.NoRespondersError, nats.errors.ConnectionClosedError,
             nats.errors.ConnectionReconnectingError, nats.js.errors.NoStreamResponseError,
             nats.js.errors.ServiceUnavailableError, nats.js.errors.ServerError, TimeoutError)
"""What a publish or a read may meet while a node dies or a leader is elected; anything else (a permissions violation,
a stream that does not take the subject) is a fault to raise, not to retry."""


def redirected_from_a_stream(message) -> bool:
    """Whether ``message`` came from a stream's consumer (its reply subject is an acknowledgement's) rather than
    from a client publishing to its subject. Whoever makes a push consumer chooses where it delivers, and the
    server checks that subject against nobody's permissions: a station allowed consumers on its own ward's stream
    could pour what a bed of its ward wrote there onto another ward's bed's confirmation or command subject. So
    confirmations, commands and what a station hears live are taken only as published; streams are read through
    the reader's own consumers."""
    return (getattr(message, "reply", None) or "").startswith("$JS.ACK.")


async def connect(urls: Sequence[str], user: str, password: str, *, ca_file: Path | None = None,
                  on_error: Callable[[Exception], Awaitable[None]] | None = None, attempts: int = -1,
                  on_disconnected: Callable[[], Awaitable[None]] | None = None,
                  on_reconnected: Callable[[], Awaitable[None]] | None = None) -> Client:
    """A connection as ``user`` to whichever node of ``urls`` answers, reconnecting to the others for ever (or
    ``attempts`` times, a refused login included, then NoServersError), with replies on the user's own inbox
    (the only one its permissions let it read). With ``ca_file``, the hospital CA, every node is reached over
    TLS (``tls://``) and must show a certificate of that CA naming its address. The server's complaints (a
    permissions violation, which drops the publish) go to ``on_error``, or to the log; ``on_disconnected`` and
    ``on_reconnected`` are told when the connection goes and comes back.

    A first connection whose TLS handshake fails (a node whose certificate is not the hospital CA's, or does not
    name its address) raises that ssl.SSLError, an OSError: nats-py 2.16 would otherwise wait for ever on the
    socket it failed to upgrade (nats-io/nats.py issue 718), trying no other node."""
    options: dict = {name: cb for name, cb in (("disconnected_cb", on_disconnected),
                                               ("reconnected_cb", on_reconnected)) if cb is not None}
    servers = list(urls)
    if ca_file is not None:
        servers, options["tls"] = tls_urls(servers), client_context(ca_file)
    handshake_failed: asyncio.Future[ssl.SSLError] = asyncio.get_running_loop().create_future()

    async def report(error: Exception) -> None:
        if isinstance(error, ssl.SSLError) and not handshake_failed.done():
            handshake_failed.set_result(error)
        await (on_error or _log_error)(error)

    connecting = asyncio.ensure_future(nats.connect(
        servers=servers, user=user, password=password, inbox_prefix=inbox_prefix(user), name=user,
        allow_reconnect=True, max_reconnect_attempts=attempts, reconnect_time_wait=RECONNECT_WAIT_S,
        connect_timeout=2, ping_interval=5, max_outstanding_pings=2, error_cb=report, **options))
    try:
        either: list[asyncio.Future[Any]] = [connecting, handshake_failed]
        await asyncio.wait(either, return_when=asyncio.FIRST_COMPLETED)
    finally:
        if not connecting.done():
            connecting.cancel()
            await asyncio.gather(connecting, return_exceptions=True)
    if connecting.cancelled():
        raise handshake_failed.result()
    handshake_failed.cancel()                       # a later failed handshake, on a reconnection, is only reported
    return connecting.result()


async def cancel_the_rest() -> None:
    """Cancel every other task of the running loop and wait for them to end: a client on a loop of its own
    leaves nothing pending when it stops that loop."""
    others = [task for task in asyncio.all_tasks() if task is not asyncio.current_task()]
    for task in others:
        task.cancel()
    await asyncio.gather(*others, return_exceptions=True)


async def _log_error(error: Exception) -> None:
    log.warning("engine connection: %s", error)


def ward_stream_config(ward: Ward, replicas: int) -> api.StreamConfig:
    """The ward's event stream: on disk, ``replicas`` copies, one copy per message id within the window."""
    return api.StreamConfig(name=stream_name(ward.name), subjects=stream_subjects(ward.name),
                            storage=api.StorageType.FILE, num_replicas=replicas,
                            retention=api.RetentionPolicy.LIMITS, duplicate_window=DUPLICATE_WINDOW_S)


def confirms_stream_config(ward: Ward, replicas: int) -> api.StreamConfig:
    """The ward's confirmation stream: on disk, ``replicas`` copies, the latest confirmation of each event and
    each notification service's record of it, for ``CONFIRMS_KEPT_S``, which a bed may read one by one (direct
    get, answered by any replica)."""
    return api.StreamConfig(name=confirms_stream_name(ward.name),
                            subjects=[bed_subject(ward.name, "*", CONFIRMED) + ".*",
                                      notified_subject(ward.name, "*", "*", "*")],
                            storage=api.StorageType.FILE, num_replicas=replicas, retention=api.RetentionPolicy.LIMITS,
                            max_msgs_per_subject=1, max_age=CONFIRMS_KEPT_S, allow_direct=True)


STREAMS_WAIT_S = 60.0
"""How long making the streams waits out a cluster still electing its leaders (just started, or a node restarting on
a busy machine): a stream call that times out or finds no leader is made again until then."""


async def ensure_ward_streams(connection: Client, hospital: Hospital, wait_s: float = STREAMS_WAIT_S) -> list[str]:
    """Create every ward's event and confirmation streams, or bring existing ones to the description; needs the
    administrator's connection. The names of the streams, each ward's two in the order of the wards. A call the
    cluster cannot answer yet is made again for ``wait_s`` (a stream made by a call whose answer was lost is then
    found and brought to the description)."""
    js = connection.jetstream()
    loop = asyncio.get_running_loop()
    give_up = loop.time() + wait_s
    names = []
    for ward in hospital.wards:
        for name, config in ((stream_name(ward.name), ward_stream_config(ward, hospital.replicas)),
                             (confirms_stream_name(ward.name), confirms_stream_config(ward, hospital.replicas))):
            while True:
                try:
                    await _ensure_stream(js, name, config)
                    break
                except RETRYABLE:
                    if loop.time() >= give_up:
                        raise
                    await asyncio.sleep(RECONNECT_WAIT_S)
            names.append(name)
    return names


async def _ensure_stream(js: JetStreamContext, name: str, config: api.StreamConfig) -> None:
    try:
        await js.stream_info(name)
    except nats.js.errors.NotFoundError:
        await js.add_stream(config)
    else:
        await js.update_stream(config)


@dataclass(frozen=True)
class Delivery:
    """One event as a station reads it: the bed, its sequence number, its kind and content."""

    bed: str
    seq: int
    kind: str
    event: dict


class BedPublisher:
    """``bed`` of ``ward`` publishing its events over ``connection`` (logged in as the bed)."""

    def __init__(self, connection: Client, ward: str, bed: str):
        self.connection, self.ward, self.bed = connection, ward, bed
        self.js = connection.jetstream()

    async def send(self, kind: str, seq: int, event: dict, *, deadline_s: float = 60.0) -> api.PubAck:
        """Publish ``event`` as number ``seq`` until the ward's stream acknowledges it (its ``duplicate`` flag set
        when an earlier attempt had already been stored), or raise TimeoutError after ``deadline_s``."""
        subject = bed_subject(self.ward, self.bed, kind)
        payload = json.dumps({**event, "bed_id": self.bed, "seq": seq}, separators=(",", ":")).encode()
        headers = {MSG_ID: f"{self.bed}:{seq}"}
        loop = asyncio.get_running_loop()
        give_up = loop.time() + deadline_s
        while True:
            try:
                return await self.js.publish(subject, payload, timeout=PUBLISH_TIMEOUT_S, headers=headers,
                                             stream=stream_name(self.ward))
            except RETRYABLE as exc:
                if loop.time() >= give_up:
                    raise TimeoutError(f"bed {self.bed}: event {seq} not acknowledged within {deadline_s} s "
                                       f"({exc!r})") from exc
                await asyncio.sleep(RECONNECT_WAIT_S)


class Ledger(Protocol):
    """What a station has applied: ``take`` records a delivery and says whether it is new (False for a number of
    that bed applied before); a station that must survive its restart keeps it on disk before it answers."""

    def take(self, delivery: Delivery) -> bool:
        """Record ``delivery``; True if its bed's number had not been taken before."""


KEPT_PER_BED = 10_000
"""Numbers a :class:`MemoryLedger` remembers of each bed: one further below the bed's highest than this counts as
taken. A bed numbers its events in order and resends only what its outbox still holds unconfirmed, never
thousands behind, so the ledger of a service that runs for months stays this size instead of growing."""


class MemoryLedger:
    """The bed numbers taken, in memory, the last KEPT_PER_BED of each bed: for services whose own journal is the
    record (a notification service) and for tools; forgotten at a restart."""

    def __init__(self) -> None:
        self._seen: dict[str, set[int]] = {}
        self._highest: dict[str, int] = {}

    def take(self, delivery: Delivery) -> bool:
        bed, seq = delivery.bed, delivery.seq
        highest = self._highest.get(bed, 0)
        seen = self._seen.setdefault(bed, set())
        if seq <= highest - KEPT_PER_BED or seq in seen:
            return False
        seen.add(seq)
        if seq > highest:
            self._highest[bed] = seq
            if len(seen) > 2 * KEPT_PER_BED:                     # forget in one sweep, not at every number
                self._seen[bed] = {n for n in seen if n > seq - KEPT_PER_BED}
        return True

    def __len__(self) -> int:
        """Numbers remembered, all beds together."""
        return sum(len(numbers) for numbers in self._seen.values())


class WardReader:
    """A station's durable pull consumer on its ward's stream: every event once, in stream order per bed.

    Each message is acknowledged to the stream only after ``ledger`` has taken it and ``handle`` (if given) has
    dealt with it, so a station that dies in between is given it again and its ledger says it was applied.
    ``delivered`` counts messages received (redeliveries included), ``duplicates`` those whose bed's number had
    been taken, ``bad`` those that are not a bed's event (dropped)."""

    def __init__(self, connection: Client, ward: str, station: str, ledger: Ledger | None = None):
        self.connection, self.ward, self.station = connection, ward, station
        self.ledger: Ledger = ledger or MemoryLedger()
        self.js = connection.jetstream()
        self.subscription: JetStreamContext.PullSubscription | None = None
        self.delivered = self.duplicates = self.bad = 0

    async def open(self) -> None:
        config = api.ConsumerConfig(ack_policy=api.AckPolicy.EXPLICIT, ack_wait=ACK_WAIT_S, max_ack_pending=1000)
        self.subscription = await self.js.pull_subscribe(
            stream_subjects(self.ward)[0].rpartition(".")[0] + ".>", durable=self.station,
            stream=stream_name(self.ward), config=config)

    async def read(self, batch: int = 100, timeout_s: float = 1.0,
                   handle: Callable[[Delivery, bool], Awaitable[None]] | None = None) -> list[Delivery]:
        """The events new to this station among the next ``batch`` messages (none within ``timeout_s``: []);
        ``handle(delivery, fresh)`` is awaited for each message, repeats included, before it is acknowledged. A
        message ``handle`` fails on, and those after it, are left unacknowledged: the stream gives them again."""
        try:
            if self.subscription is None:
                await self.open()
            assert self.subscription is not None
            messages = await self.subscription.fetch(batch, timeout=timeout_s)
        except RETRYABLE:           # nothing new, or the stream or consumer is electing a leader: ask again later
            return []
        fresh = []
        for message in messages:
            self.delivered += 1
            try:
                delivery = self._delivery(message)
            except ValueError as exc:               # json's errors are ValueErrors
                self.bad += 1
                log.warning("ward %s: message on %s dropped: %s", self.ward, message.subject, exc)
                await message.ack()                 # given again, it would be as bad
                continue
            new = self.ledger.take(delivery)
            if new:
                fresh.append(delivery)
            else:
                self.duplicates += 1
            if handle is not None:
                try:
                    await handle(delivery, new)
                except RETRYABLE as exc:
                    log.warning("ward %s: %s's event %d not handled yet (%r): given again later", self.ward,
                                delivery.bed, delivery.seq, exc)
                    break
            await message.ack()
        return fresh

    @staticmethod
    def _delivery(message) -> Delivery:
        """The event in ``message``; a ValueError when it is not one. The bed is the one whose subject it came on
        (each bed may publish only its own), so a bed cannot spend another's numbers."""
        _, _, bed, kind = message.subject.split(".", 3)
        sender, seq = parse_message_id((message.headers or {}).get(MSG_ID, ""))
        if sender != bed:
            raise ValueError(f"{MSG_ID} names bed {sender!r}, but it came on {bed!r}'s subject")
        event = json.loads(message.data)
        if not isinstance(event, dict):
            raise ValueError(f"an event must be a JSON object, got {type(event).__name__}")
        return Delivery(bed, seq, kind, event)
