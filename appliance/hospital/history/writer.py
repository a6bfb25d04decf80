"""The history writer: every ward's stream through its own durable consumer into PostgreSQL, acknowledged only
after the transaction committed, and the beds' summaries down-sampled to minutes.

Events: one pull consumer per ward stream, named ``hospital-history`` (no bed or station may take the name).
A fetched batch is written in one transaction (``store.write_events``) and only then acknowledged; a writer
killed in between gets the batch again after ``ack_wait_s`` and the keys already taken drop it, so each
``(bed_id, seq)`` is in the table once. Summaries: a plain subscription in the queue group
``hospital-history`` (several writers share the beds between them), not a stream: storing 3,000 summaries a
second on three fsyncing nodes would cost the engine more than the alarms it is there for, and a trend may
miss the seconds a writer was down, which its ``samples`` column then shows. Finished minutes are written
every ``flush_every_s``; the partitions ahead are made and the expired ones dropped every ``housekeeping_s``.
The database work runs on threads, one transaction at a time on the one connection.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import json
import logging
import threading
import time
from collections.abc import Callable

import nats.js.errors
import psycopg
from nats.aio.client import Client
from nats.aio.msg import Msg
from nats.js import JetStreamContext, api

from appliance.hospital.description import Hospital, HistoryPolicy
from appliance.hospital.engine import RETRYABLE
from appliance.hospital.history.schema import create_schema, drop_expired, ensure_ahead
from appliance.hospital.history.store import StoredEvent, write_events, write_minutes
from appliance.hospital.history.trend import Minute, MinuteTrend
from appliance.hospital.nodeconfig import HISTORY
from appliance.hospital.subjects import MSG_ID, ROOT, SUMMARY, bed_subject, parse_message_id, stream_name

log = logging.getLogger(__name__)

FETCH_BATCH = 500
ACK_WAIT_S = 10.0
"""How long a fetched batch may stay unacknowledged before it is delivered again: a batch commits in well under a
second, and a writer started again after a crash gets what the dead one held after this long."""
FLUSH_EVERY_S = 10.0
HOUSEKEEPING_S = 3600.0
STREAM_WAIT_S = 10.0


class HistoryWriter:
    """Writes ``hospital``'s events and pressure minutes into ``db`` from ``connection`` (logged in as
    ``hospital-history``). ``stored`` counts events new to the table, ``duplicates`` those already there,
    ``heard`` summaries counted into minutes, ``rejected`` messages that were not an event of the bed and number
    their subject and id say, or not a summary."""

    def __init__(self, db: psycopg.Connection, connection: Client, hospital: Hospital, *,
                 ack_wait_s: float = ACK_WAIT_S, flush_every_s: float = FLUSH_EVERY_S,
                 housekeeping_s: float = HOUSEKEEPING_S, clock: Callable[[], float] = time.time):
        if hospital.history is None:
            raise ValueError("the hospital description has no [history] table: the history writer needs its "
                             "retention policy (events_days, pressure_days)")
        self.policy: HistoryPolicy = hospital.history
        self.db, self.connection, self.hospital = db, connection, hospital
        self.js = connection.jetstream()
        self.ack_wait_s, self.flush_every_s, self.housekeeping_s = ack_wait_s, flush_every_s, housekeeping_s
        self.clock = clock
        self.trend = MinuteTrend()
        self.unwritten: list[Minute] = []
        self.stored = self.duplicates = self.heard = self.rejected = 0
        self._db_lock = threading.Lock()
        self._stopping = asyncio.Event()

    async def run(self) -> None:
        """Write until :meth:`stop`; the finished and unfinished minutes are written on the way out."""
        await self._on_db(create_schema, self.db)
        summaries = await self.connection.subscribe(bed_subject("*", "*", SUMMARY), queue=HISTORY,
                                                    cb=self._summary)
        tasks = [asyncio.create_task(self._consume(ward.name), name=f"history {ward.name}")
                 for ward in self.hospital.wards]
        tasks.append(asyncio.create_task(self._housekeeping(), name="history housekeeping"))
        try:
            while not self._stopping.is_set():
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._stopping.wait(), self.flush_every_s)
                await self.flush(self.clock())
                for task in tasks:
                    if task.done():
                        task.result()           # a task that died raises its error here
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            await summaries.unsubscribe()
            await self.flush(None)

    def stop(self) -> None:
        self._stopping.set()

    async def subscribe(self, ward: str) -> JetStreamContext.PullSubscription:
        """The writer's durable consumer on ``ward``'s stream."""
        config = api.ConsumerConfig(ack_policy=api.AckPolicy.EXPLICIT, ack_wait=self.ack_wait_s,
                                    max_ack_pending=10 * FETCH_BATCH)
        return await self.js.pull_subscribe(f"{ROOT}.{ward}.>", durable=HISTORY, stream=stream_name(ward),
                                            config=config)

    async def step(self, subscription: JetStreamContext.PullSubscription, ward: str, timeout_s: float = 1.0) -> int:
        """Fetch, store and then acknowledge one batch of ``ward``'s events; how many messages it held."""
        try:
            messages = await subscription.fetch(FETCH_BATCH, timeout=timeout_s)
        except RETRYABLE:
            return 0
        events = [event for message in messages if (event := self._event(ward, message)) is not None]
        fresh = await self._on_db(write_events, self.db, events)
        self.stored += fresh
        self.duplicates += len(events) - fresh
        await self.acknowledge(messages)
        return len(messages)

    async def acknowledge(self, messages: list[Msg]) -> None:
        """Acknowledge a batch whose events are committed."""
        for message in messages:
            await message.ack()

    async def flush(self, now_s: float | None) -> None:
        """Write the minutes finished by ``now_s`` (all when None), keeping them for the next try if that fails."""
        self.unwritten += self.trend.take(now_s)
        if not self.unwritten:
            return
        try:
            await self._on_db(write_minutes, self.db, self.unwritten)
        except psycopg.OperationalError as exc:
            log.error("history: %d pressure minute(s) not written, kept for the next try: %s", len(self.unwritten), exc)
        else:
            self.unwritten = []

    async def housekeeping(self, now: dt.datetime) -> list[str]:
        """Make the partitions ahead of ``now`` and drop those past the retention; the names dropped."""
        await self._on_db(ensure_ahead, self.db, now)
        dropped = await self._on_db(drop_expired, self.db, now, self.policy.events_days, self.policy.pressure_days)
        if dropped:
            log.info("history: dropped partitions past the retention: %s", ", ".join(dropped))
        return dropped

    async def _consume(self, ward: str) -> None:
        subscription = None
        while subscription is None:
            try:
                subscription = await self.subscribe(ward)
            except RETRYABLE:                       # the stream is electing a leader: ask again
                await asyncio.sleep(1.0)
            except nats.js.errors.NotFoundError:
                log.warning("history: ward %s has no stream yet (appliance hospital streams makes it)", ward)
                await asyncio.sleep(STREAM_WAIT_S)
        while True:
            await self.step(subscription, ward)

    async def _housekeeping(self) -> None:
        while True:
            await self.housekeeping(dt.datetime.fromtimestamp(self.clock(), dt.UTC))
            await asyncio.sleep(self.housekeeping_s)

    def _event(self, ward: str, message: Msg) -> StoredEvent | None:
        try:
            bed, seq = parse_message_id((message.headers or {}).get(MSG_ID, ""))
            _, _, subject_bed, kind = message.subject.split(".")
            body = json.loads(message.data)
            if subject_bed != bed or not isinstance(body, dict) or body.get("bed_id") != bed or body.get("seq") != seq:
                raise ValueError(f"the body's bed_id and seq {body.get('bed_id')!r}:{body.get('seq')!r} are not "
                                 f"its subject's and id's {subject_bed}:{seq}")
        except ValueError as exc:
            self.rejected += 1
            log.error("history: %s on %s is not an event, not stored: %s", message.data[:200], message.subject, exc)
            return None
        return StoredEvent(message.metadata.timestamp, ward, bed, seq, kind, body)

    async def _summary(self, message: Msg) -> None:
        try:
            _, ward, bed, _ = message.subject.split(".")
            body = json.loads(message.data)
            if not isinstance(body, dict):
                raise ValueError(f"a summary must be a JSON object, got {type(body).__name__}")
            self.trend.add(ward, bed, self.clock(), body)
            self.heard += 1
        except ValueError as exc:
            self.rejected += 1
            log.warning("history: summary on %s not counted: %s", message.subject, exc)

    async def _on_db(self, work, *args):
        return await asyncio.to_thread(self._locked, work, *args)

    def _locked(self, work, *args):
        """One piece of database work at a time: a thread lock, because a task cancelled on the way out leaves its
        thread running, and the last flush must not begin a transaction inside that thread's."""
        with self._db_lock:
            return work(*args)

