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
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass

import nats
import nats.errors
import nats.js.errors
from nats.aio.client import Client
from nats.js import JetStreamContext, api

from appliance.hospital.description import Hospital, Ward
from appliance.hospital.nodeconfig import DUPLICATE_WINDOW_S
from appliance.hospital.subjects import (MSG_ID, bed_subject, inbox_prefix, parse_message_id, stream_name,
                                         stream_subjects)

log = logging.getLogger(__name__)

RECONNECT_WAIT_S = 0.25
PUBLISH_TIMEOUT_S = 2.0
"""How long one publish waits for the stream's acknowledgement before it is sent again: a leader's election
after a node's death takes a few seconds, during which publishes time out."""
RETRYABLE = (nats.errors.TimeoutError, nats.errors.NoRespondersError, nats.errors.ConnectionClosedError,
             nats.errors.ConnectionReconnectingError, nats.js.errors.NoStreamResponseError,
             nats.js.errors.ServiceUnavailableError, nats.js.errors.ServerError, TimeoutError)
"""What a publish or a read may meet while a node dies or a leader is elected; anything else (a permissions violation,
a stream that does not take the subject) is a fault to raise, not to retry."""


async def connect(urls: Sequence[str], user: str, password: str, *,
                  on_error: Callable[[Exception], Awaitable[None]] | None = None, attempts: int = -1) -> Client:
    """A connection as ``user`` to whichever node of ``urls`` answers, reconnecting to the others for ever (or
    ``attempts`` times, a refused login included, then NoServersError), with replies on the user's own inbox
    (the only one its permissions let it read). The server's complaints (a permissions violation, which drops
    the publish) go to ``on_error``, or to the log."""
    return await nats.connect(servers=list(urls), user=user, password=password, inbox_prefix=inbox_prefix(user),
                              name=user, allow_reconnect=True, max_reconnect_attempts=attempts,
                              reconnect_time_wait=RECONNECT_WAIT_S, connect_timeout=2, ping_interval=5,
                              max_outstanding_pings=2, error_cb=on_error or _log_error)


async def _log_error(error: Exception) -> None:
    log.warning("engine connection: %s", error)


def ward_stream_config(ward: Ward, replicas: int) -> api.StreamConfig:
    """The ward's event stream: on disk, ``replicas`` copies, one copy per message id within the window."""
    return api.StreamConfig(name=stream_name(ward.name), subjects=stream_subjects(ward.name),
                            storage=api.StorageType.FILE, num_replicas=replicas,
                            retention=api.RetentionPolicy.LIMITS, duplicate_window=DUPLICATE_WINDOW_S)


async def ensure_ward_streams(connection: Client, hospital: Hospital) -> list[str]:
    """Create every ward's stream, or bring an existing one to the description; needs the administrator's
    connection. The names of the streams, in the order of the wards."""
    js = connection.jetstream()
    names = []
    for ward in hospital.wards:
        name = stream_name(ward.name)
        config = ward_stream_config(ward, hospital.replicas)
        try:
            await js.stream_info(name)
        except nats.js.errors.NotFoundError:
            await js.add_stream(config)
        else:
            await js.update_stream(config)
        names.append(name)
    return names


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


class WardReader:
    """A station's durable pull consumer on its ward's stream: every event once, in stream order per bed.

    ``delivered`` counts messages received (redeliveries included), ``duplicates`` those dropped because that
    bed's number had been applied; ``applied`` maps each bed to its numbers in the order applied."""

    def __init__(self, connection: Client, ward: str, station: str):
        self.connection, self.ward, self.station = connection, ward, station
        self.js = connection.jetstream()
        self.subscription: JetStreamContext.PullSubscription | None = None
        self.applied: dict[str, list[int]] = {}
        self._seen: dict[str, set[int]] = {}
        self.delivered = 0
        self.duplicates = 0

    async def open(self) -> None:
        config = api.ConsumerConfig(ack_policy=api.AckPolicy.EXPLICIT, ack_wait=10.0, max_ack_pending=1000)
        self.subscription = await self.js.pull_subscribe(
            stream_subjects(self.ward)[0].rpartition(".")[0] + ".>", durable=self.station,
            stream=stream_name(self.ward), config=config)

    async def read(self, batch: int = 100, timeout_s: float = 1.0) -> list[Delivery]:
        """The events new to this station among the next ``batch`` messages (none within ``timeout_s``: [])."""
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
            bed, seq = parse_message_id((message.headers or {}).get(MSG_ID, ""))
            if seq in self._seen.setdefault(bed, set()):
                self.duplicates += 1
            else:
                self._seen[bed].add(seq)
                self.applied.setdefault(bed, []).append(seq)
                fresh.append(Delivery(bed, seq, message.subject.rpartition(".")[2], json.loads(message.data)))
            await message.ack()
        return fresh
