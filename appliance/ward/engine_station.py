"""The ward station on the hospital engine: its ward's events from the ward's replicated stream, each applied
once, journalled, and confirmed to its bed only once the confirmation is itself on a quorum.

For each event the station reads through its durable consumer (``appliance.hospital.engine.WardReader``), in
this order: the event is written to the station's journal (:class:`~appliance.ward.applied.AppliedJournal`, on
disk), shown (:class:`~appliance.ward.board.WardBoard`), its confirmation stored in the ward's confirmation
stream and acknowledged there by a quorum, then sent to the bed on its ``confirm`` subject, and only then is the
event acknowledged to the stream. A station that dies anywhere in between is given the event again when it is
back; its journal says it was applied, so it is confirmed again and not shown twice. A repeat (a resend of a bed
that missed its confirmation) is confirmed again too.

Status and summaries come as plain messages (each replaces the last; nothing is lost that matters when one is
missed). With a command journal the station's nurses act on its beds as on an MQTT ward
(:class:`~appliance.ward.commands.CommandSender`: journalled, sent again until answered or expired): each
command goes to the bed's ``command`` subject and the answers come from the ward's ``command-result`` subjects,
plain messages both. What is pending goes again at once when the station connects and when its bed says it is
online. The engine lets a station send commands only to the beds of its own ward.

The records of the ward's notification services (``appliance.hospital.notify``: an alarm change paged to the
phones, or refused by their gateway) are shown with their alarms. They are heard as they are stored, and each
time the station (re)connects it also reads back those of the last ``PAGES_LOOK_BACK_S`` from the ward's
confirmation stream, through a consumer of its own filtered on them that it reads to the end: so a station
restarted, or cut off for a while, shows the pages it would have shown had it run on, and the board shows a
record heard twice once. Live records come on the plain subscription, which needs no consumer kept alive across
a node's death. Each service's word on whether its pages go out is heard the same way (plain, repeated), and the
board shows a service gone quiet as unknown.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime
import json
import logging
import sqlite3
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import nats.errors
import nats.js.errors
from nats.aio.client import Client
from nats.js import api

from appliance.hospital.engine import (RETRYABLE, Delivery, WardReader, cancel_the_rest, connect,
                                      redirected_from_a_stream)
from appliance.hospital.subjects import (CONFIRM, answer_subject, bed_subject, command_subject, confirmation_subject,
                                         confirms_stream_name, notified_subject, paging_status_subject)
from appliance.ward.applied import AppliedJournal
from appliance.ward.board import EVENTS_KEPT, WardBoard
from appliance.ward.commands import DEFAULT_EXPIRY_S, DEFAULT_RESEND_S, CommandSender
from appliance.ward.config import WardConfig
from appliance.ward.journal import CommandJournal

log = logging.getLogger(__name__)

CONFIRM_TIMEOUT_S = 2.0
"""How long the station waits for the confirmation stream's acknowledgement before it leaves the event to be
given again."""
RETRY_S = 0.5
CONNECT_RETRY_S = 2.0
PAGES_LOOK_BACK_S = 24 * 3600.0
"""How far back a station reads the page records when it (re)connects. The board shows a page only with its
alarm while that is open, and keeps the latest record of each alarm and service: a day covers every alarm a
shift can still have open, while the whole confirmation stream (a week) would be read at every start mostly for
alarms long ended. An alarm open for longer than this shows no page after a restart."""
READ_BACK_BATCH = 200
READ_BACK_WAIT_S = 1.0
"""How long the read-back waits for a record before it takes the look-back to hold no more."""
READ_BACK_RETRY_MAX_S = 60.0
READ_BACK_IDLE_S = 30.0
"""The engine drops the read-back's consumer once it is read from no more for this long (a station may not
delete consumers)."""


class EngineStation:
    """Station ``station`` of ward ``ward`` on the engine's nodes at ``urls``, logged in with ``password`` (over TLS
    trusting the hospital CA ``ca_file`` if given); what it
    applied is kept in ``journal`` (which the caller closes). Counters: ``confirmations_sent``; ``board`` holds
    the beds. ``command_journal`` lets its nurses send commands to beds (``commands``, a :class:`CommandSender`,
    is None without one); ``command_expiry_s`` and ``resend_after_s`` are its timings."""

    def __init__(self, urls: Sequence[str], ward: str, station: str, password: str, journal: AppliedJournal, *,
                 ca_file: Path | None = None, summary_interval_s: float = 1.0, stale_after_s: float | None = None,
                 command_journal: CommandJournal | None = None, command_expiry_s: float = DEFAULT_EXPIRY_S,
                 resend_after_s: float = DEFAULT_RESEND_S):
        self.urls, self.ward, self.station, self._password, self.journal = list(urls), ward, station, password, \
            journal
        self.ca_file = ca_file
        self.board = WardBoard(summary_interval_s, stale_after_s)
        self.stale_after_s = self.board.stale_after_s
        self.confirmations_sent = 0
        self.commands = None if command_journal is None else CommandSender(
            command_journal, self._publish_command, station, expiry_s=command_expiry_s,
            resend_after_s=resend_after_s, on_change=self.board.changed)
        for delivery in journal.latest(EVENTS_KEPT):         # what it showed before a restart
            self.board.restore(delivery.bed, delivery.event)
        self._ready = threading.Event()
        self._stopping = False
        self._connection: Client | None = None
        self._read_back: asyncio.Task | None = None
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="ward-station-engine", daemon=True)
        self._thread.start()
        asyncio.run_coroutine_threadsafe(self._run(), self._loop)

    @classmethod
    def from_config(cls, config: WardConfig, journal: AppliedJournal,
                    command_journal: CommandJournal | None = None) -> EngineStation:
        engine = config.engine
        if engine is None:
            raise ValueError("the configuration names a broker, not the hospital engine: use WardStation")
        return cls(engine.servers, engine.ward, config.client_id, engine.password(), journal, ca_file=engine.ca_file,
                   summary_interval_s=config.summary_interval_s, command_journal=command_journal,
                   command_expiry_s=config.command_expiry_s)

    @property
    def connected(self) -> bool:
        """Connected to the engine and reading the ward's stream."""
        return self._ready.is_set()

    @property
    def version(self) -> int:
        return self.board.version

    def wait_subscribed(self, timeout_s: float = 10.0) -> bool:
        """True once the station reads its ward, False if that took more than ``timeout_s``."""
        return self._ready.wait(timeout_s)

    def beds(self, *, events: bool = True) -> list[dict]:
        """Every bed, alarming ones first (:meth:`WardBoard.beds`)."""
        return self.board.beds(events=events)

    def online_flags(self) -> tuple[bool, ...]:
        return self.board.online_flags()

    def paging(self) -> list[dict]:
        """Whether each notification service of the ward gets pages out (:meth:`WardBoard.paging`)."""
        return self.board.paging()

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop reading and disconnect; what was not acknowledged is given again at the next start, and commands
        not yet answered stay in their journal, sent again then."""
        if self.commands is not None:
            self.commands.close()

        async def finish() -> None:
            self._stopping = True                   # nats-py can turn a cancellation into a timeout
            if self._connection is not None:
                await self._connection.close()
            await cancel_the_rest()

        try:
            asyncio.run_coroutine_threadsafe(finish(), self._loop).result(timeout_s)
        except (TimeoutError, nats.errors.Error) as exc:
            log.warning("ward: the engine connection did not close cleanly: %r", exc)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout_s)
        if not self._thread.is_alive():
            self._loop.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # The engine's thread.

    async def _run(self) -> None:
        while not self._stopping:
            try:
                self._connection = connection = await connect(self.urls, self.station, self._password,
                                                              ca_file=self.ca_file, on_disconnected=self._down,
                                                              on_reconnected=self._up)
                break
            except (nats.errors.Error, OSError) as exc:      # a refused login: ward IT may be adding the station
                log.error("ward: the hospital engine refused station %s: %r", self.station, exc)
                await asyncio.sleep(CONNECT_RETRY_S)
        else:
            return
        for kind in ("status", "summary"):
            await connection.subscribe(bed_subject(self.ward, "*", kind), cb=self._on_bed_message)
        await connection.subscribe(notified_subject(self.ward, "*", "*", "*"), cb=self._on_page)
        await connection.subscribe(paging_status_subject(self.ward, "*"), cb=self._on_paging)
        self._read_pages_back()
        if self.commands is not None:
            # the engine takes this before any command the station publishes after it, so no answer is missed
            await connection.subscribe(answer_subject(self.ward, "*"), cb=self._on_answer)
            self.commands.connected(True)
        reader = WardReader(connection, self.ward, self.station, ledger=self.journal)
        while not self._stopping:
            try:
                if reader.subscription is None:
                    await reader.open()
                    self._ready.set()
                await reader.read(handle=self._handle)
            except RETRYABLE as exc:
                log.warning("ward: the ward's stream is not readable now: %r", exc)
                await asyncio.sleep(RETRY_S)
            except sqlite3.Error as exc:        # what was not journalled is not acknowledged: given again
                log.error("ward: the journal of applied events refuses writes: %s", exc)
                await asyncio.sleep(CONNECT_RETRY_S)

    async def _down(self) -> None:
        self._ready.clear()
        if self.commands is not None:
            self.commands.connected(False)

    async def _up(self) -> None:
        self._ready.set()
        self._read_pages_back()
        if self.commands is not None:
            self.commands.connected(True)

    def _published(self, message) -> bool:
        """False, counted as refused, for a message a stream's consumer poured onto a subject the station hears
        (:func:`~appliance.hospital.engine.redirected_from_a_stream`)."""
        if redirected_from_a_stream(message):
            self.board.refused(message.subject, ValueError(f"delivered from a stream ({message.reply}), not published"))
            return False
        return True

    async def _on_bed_message(self, message) -> None:
        if not self._published(message):
            return
        _, _, bed, kind = message.subject.split(".", 3)
        body = self.board.take(bed, kind, message.data)
        if kind == "status" and body == "online" and self.commands is not None:
            await asyncio.to_thread(self.commands.bed_online, bed)

    async def _on_page(self, message) -> None:
        if self._published(message):
            self.board.take_page(message.subject.split(".")[2], message.data)

    async def _on_paging(self, message) -> None:
        if self._published(message):
            self.board.take_paging(message.subject.rpartition(".")[2], message.data)

    def _read_pages_back(self) -> None:
        """Start reading the page records of the look-back, again from its start if a read was under way."""
        if self._read_back is not None:
            self._read_back.cancel()
        self._read_back = asyncio.create_task(self._read_back_pages(), name="ward-station page read-back")

    async def _read_back_pages(self) -> None:
        """Every page record of the last ``PAGES_LOOK_BACK_S`` onto the board, tried again, less and less often,
        until it is read (an engine whose permissions predate the read-back answers nothing)."""
        wait_s = CONNECT_RETRY_S
        while not self._stopping:
            try:
                await self._read_back_once()
                return
            except nats.js.errors.NotFoundError:
                log.warning("ward: ward %s has no confirmation stream yet (appliance hospital streams makes it): "
                            "no page records read back", self.ward)
                return
            except (*RETRYABLE, nats.errors.Error) as exc:      # the live records still come, older ones wait
                log.warning("ward: the page records are not readable now (%r): trying again in %.0f s", exc, wait_s)
                await asyncio.sleep(wait_s)
                wait_s = min(2 * wait_s, READ_BACK_RETRY_MAX_S)

    async def _read_back_once(self) -> None:
        assert self._connection is not None
        start = datetime.datetime.now(datetime.UTC) - datetime.timedelta(seconds=PAGES_LOOK_BACK_S)
        config = api.ConsumerConfig(ack_policy=api.AckPolicy.NONE, deliver_policy=api.DeliverPolicy.BY_START_TIME,
                                    opt_start_time=start, mem_storage=True, num_replicas=1,
                                    inactive_threshold=READ_BACK_IDLE_S)
        subscription = await self._connection.jetstream().pull_subscribe(
            notified_subject(self.ward, "*", "*", "*"), stream=confirms_stream_name(self.ward), config=config)
        try:
            while True:
                try:
                    messages = await subscription.fetch(READ_BACK_BATCH, timeout=READ_BACK_WAIT_S)
                except nats.errors.TimeoutError:
                    return                              # no more records in the look-back
                for message in messages:
                    self.board.take_page(message.subject.split(".")[2], message.data)
                if messages[-1].metadata.num_pending == 0:
                    return
        finally:
            with contextlib.suppress(nats.errors.Error):       # a closed connection took the subscription with it
                await subscription.unsubscribe()

    async def _on_answer(self, message) -> None:
        """A bed's answer to a command, into the command journal off the engine's thread; a bad one is counted."""
        assert self.commands is not None
        if not self._published(message):
            return
        bed = message.subject.split(".")[2]
        try:
            await asyncio.to_thread(self.commands.take_answer, bed, message.data)
        except (ValueError, TypeError, UnicodeDecodeError) as exc:     # json's errors are ValueErrors
            self.board.refused(message.subject, exc)
        except sqlite3.Error as exc:                  # the bed answers the next resend too
            log.error("ward: %s's answer not journalled: %s", bed, exc)

    def _publish_command(self, bed: str, payload: str) -> bool:
        """Hand a command to the engine's thread without waiting; False when the station is not connected."""
        connection = self._connection
        if connection is None or not connection.is_connected:
            return False
        asyncio.run_coroutine_threadsafe(connection.publish(command_subject(self.ward, bed), payload.encode()),
                                         self._loop)
        return True

    async def _handle(self, delivery: Delivery, fresh: bool) -> None:
        """Show a new event, then confirm it (a repeat too) durably, then to the bed; raises when the engine
        cannot keep the confirmation, so the event is given again."""
        if fresh and self.board.take(delivery.bed, delivery.kind, json.dumps(delivery.event).encode()) is None:
            return                                  # refused as bad: never confirmed
        assert self._connection is not None
        payload = json.dumps({"seq": delivery.seq, "station": self.station, "confirmed_at": time.time()}).encode()
        await self._connection.jetstream().publish(confirmation_subject(self.ward, delivery.bed, delivery.seq),
                                                   payload, timeout=CONFIRM_TIMEOUT_S,
                                                   stream=confirms_stream_name(self.ward))
        await self._connection.publish(bed_subject(self.ward, delivery.bed, CONFIRM), payload)
        self.confirmations_sent += 1
