"""The ward link over the hospital engine: the bed's events into its ward's replicated stream, the ward
station's confirmations back, with the link's outbox, resends and technical alarms (``appliance.alerts.wardlink``)
unchanged.

An event is held once the ward's stream acknowledges it, which it does only when a quorum of its replicas has
it on disk (:class:`~appliance.hospital.engine.BedPublisher`, one attempt per send: the link decides when to send
again). It is confirmed when a ward station says so on the bed's ``confirm`` subject, which the station does only
after it has journalled the event and stored the confirmation itself in the ward's confirmation stream on a
quorum. A resend inside the stream's duplicate window is acknowledged as a duplicate and never reaches the
station again, so for a duplicate the bed looks the confirmation up in that stream: a confirmation lost on its
way (the bed was away) is found there.

The station's commands come on the bed's ``command`` subject and its answers go back on ``command-result``, both
plain messages, as summaries are: no stream needs to keep them, since the station sends a command again until
it has the answer, and the bed answers a repeat from its store. The subscription is made, and renewed by the
client on every reconnection, before the bed says it is online: the station's cue to send what waits for it.

The native client runs on an event loop of its own thread (:class:`EngineLoop`); the link's threads hand it work
and never wait for the network. A bed has one loop to itself; a process holding many beds' links (a gateway for
beds that cannot reach the engine themselves, or a ward simulated on one machine) gives them one loop to share,
since a loop and its thread pool per bed would be thousands of threads for the same work.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import json
import logging
import threading
from collections.abc import Coroutine, Sequence
from pathlib import Path

import nats.errors
import nats.js.errors
from nats.aio.client import Client

from appliance.alerts.wardlink import WardLink
from appliance.hospital.engine import RETRYABLE, BedPublisher, cancel_the_rest, connect, redirected_from_a_stream
from appliance.hospital.subjects import (CONFIRM, answer_subject, bed_subject, command_subject, confirmation_subject,
                                         confirms_stream_name)
from appliance.store.outbox import Outbox

log = logging.getLogger(__name__)

CONNECT_RETRY_S = 1.0


class EngineLoop:
    """An asyncio event loop running on a daemon thread of its own, for one or many engine transports."""

    def __init__(self):
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name="ward-link-engine", daemon=True)
        self._thread.start()

    def close(self, timeout_s: float) -> None:
        """Stop the loop (whatever still runs on it is dropped) and close it once its thread has ended."""
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(timeout_s)
        if not self._thread.is_alive():
            self.loop.close()


class EngineTransport:
    """Bed ``bed`` of ward ``ward`` on the engine's nodes at ``urls``, logged in as the bed with ``password``, over
    TLS trusting ``ca_file`` if given; on ``engine_loop`` if given (left running at close, for the other beds on
    it), else on a loop of its own."""

    peer = "the hospital engine"

    def __init__(self, urls: Sequence[str], ward: str, bed: str, password: str, *, ca_file: Path | None = None,
                 engine_loop: EngineLoop | None = None):
        if not urls:
            raise ValueError("the hospital engine needs at least one node's address")
        self.urls, self.ward, self.bed, self._password, self.ca_file = list(urls), ward, bed, password, ca_file
        self._link: WardLink | None = None
        self._connection: Client | None = None
        self._publisher: BedPublisher | None = None
        self._up = self._stopping = False
        self._own_loop = engine_loop is None
        self._engine_loop = engine_loop
        self._work: set[concurrent.futures.Future] = set()      # this bed's coroutines on the loop, not yet done

    def start(self, link: WardLink) -> None:
        self._link = link
        if self._engine_loop is None:
            self._engine_loop = EngineLoop()
        self._submit(self._connect())

    def send_event(self, seq: int, event: dict) -> bool:
        if not self._up or self._publisher is None:
            return False
        self._submit(self._send(self._publisher, seq, event))
        return True

    def send_summary(self, payload: str) -> bool:
        return self._fire(bed_subject(self.ward, self.bed, "summary"), payload.encode())

    def send_answer(self, payload: str) -> bool:
        """Publish an answer without an acknowledgement: one lost is asked for again by the station's resend."""
        return self._fire(answer_subject(self.ward, self.bed), payload.encode())

    def connected(self) -> bool:
        return self._up

    def close(self, timeout_s: float) -> None:
        async def finish() -> None:
            self._stopping = True                   # nats-py can turn a cancellation into a timeout
            if self._connection is not None:
                if self._connection.is_connected:
                    await self._connection.publish(bed_subject(self.ward, self.bed, "status"), b"offline")
                await self._connection.close()
            if self._own_loop:
                await cancel_the_rest()

        if self._engine_loop is None:
            return                                      # never started
        try:
            asyncio.run_coroutine_threadsafe(finish(), self._engine_loop.loop).result(timeout_s)
        except (TimeoutError, nats.errors.Error) as exc:
            log.warning("ward link: the engine connection did not close cleanly: %r", exc)
        for work in list(self._work):                   # a connection still being tried, a send on its way
            work.cancel()
        if self._own_loop:
            self._engine_loop.close(timeout_s)

    def _submit(self, work: Coroutine) -> None:
        """Run ``work`` on the loop, kept track of until it ends so that close can cancel it."""
        assert self._engine_loop is not None
        future = asyncio.run_coroutine_threadsafe(work, self._engine_loop.loop)
        self._work.add(future)
        future.add_done_callback(self._work.discard)

    def _bed(self) -> WardLink:
        if self._link is None:
            raise RuntimeError("the engine transport has not been started by a ward link")
        return self._link

    def _fire(self, subject: str, payload: bytes) -> bool:
        """Publish without an acknowledgement (a summary, a status): lost when the connection is."""
        if not self._up or self._connection is None:
            return False
        self._submit(self._connection.publish(subject, payload))
        return True

    # The engine's thread.

    async def _connect(self) -> None:
        while not self._stopping:
            try:
                connection = await connect(self.urls, self.bed, self._password, ca_file=self.ca_file,
                                           on_error=self._on_error,
                                           on_disconnected=self._on_disconnected,
                                           on_reconnected=self._on_reconnected)
                break
            except (nats.errors.Error, OSError) as exc:     # a refused login: ward IT may be adding the bed
                log.warning("ward link: the hospital engine refused the bed: %r", exc)
                await asyncio.sleep(CONNECT_RETRY_S)
        else:
            return
        self._connection, self._publisher = connection, BedPublisher(connection, self.ward, self.bed)
        await connection.subscribe(bed_subject(self.ward, self.bed, CONFIRM), cb=self._on_confirm)
        await connection.subscribe(command_subject(self.ward, self.bed), cb=self._on_command)
        await self._on_reconnected()

    async def _on_reconnected(self) -> None:
        assert self._connection is not None
        try:
            await self._connection.publish(bed_subject(self.ward, self.bed, "status"), b"online")
            await self._connection.flush(timeout=2)
        except (nats.errors.Error, TimeoutError) as exc:
            log.warning("ward link: the engine connection is not ready: %r", exc)
            return
        self._up = True
        self._bed().transport_ready()

    async def _on_disconnected(self) -> None:
        if self._up:
            log.warning("ward link: the connection to the hospital engine was lost; reconnecting")
        self._up = False
        self._bed().transport_down()

    async def _on_error(self, error: Exception) -> None:
        """Failed reconnections are only noted (the link's technical alarm says the engine is unreachable); the
        server's complaints, such as a permissions violation, are warned of."""
        log.log(logging.DEBUG if isinstance(error, (OSError, *RETRYABLE, nats.errors.UnexpectedEOF)) else
                logging.WARNING, "ward link: engine connection: %r", error)

    async def _send(self, publisher: BedPublisher, seq: int, event: dict) -> None:
        link = self._bed()
        try:
            ack = await publisher.send(event["type"], seq, event, deadline_s=0)
        except (TimeoutError, *RETRYABLE) as exc:
            log.info("ward link: event %d not acknowledged by the engine: %r", seq, exc)
            link.transport_failed(seq)
            return
        link.transport_held(seq)
        if ack.duplicate:                       # stored before: its confirmation may be waiting in the engine
            await self._look_up_confirmation(seq)

    async def _look_up_confirmation(self, seq: int) -> None:
        assert self._connection is not None
        try:
            found = await self._connection.jetstream().get_last_msg(
                confirms_stream_name(self.ward), confirmation_subject(self.ward, self.bed, seq), direct=True)
        except (nats.js.errors.NotFoundError, *RETRYABLE):
            return                              # not confirmed yet, or not now: the station's word will come
        await self._take_confirmation(found.data or b"")

    async def _on_confirm(self, message) -> None:
        if not _redirected(message):
            await self._take_confirmation(message.data)

    async def _on_command(self, message) -> None:
        if not _redirected(message):
            self._bed().transport_command(message.data)

    async def _take_confirmation(self, data: bytes) -> None:
        try:
            body = json.loads(data)
            seq, station = body["seq"], body["station"]
        except (ValueError, TypeError, KeyError) as exc:
            log.warning("ward link: bad confirmation ignored: %s", exc)
            return
        await asyncio.to_thread(self._bed().transport_confirmed, seq, station)


def _redirected(message) -> bool:
    """A confirmation or command a stream's consumer poured onto the bed's subject, refused with a warning."""
    if redirected_from_a_stream(message):
        log.warning("ward link: refused a message on %s delivered from a stream (%s), not published by a station",
                    message.subject, message.reply)
        return True
    return False


def engine_ward_link(urls: Sequence[str], ward: str, bed: str, password: str, outbox: Outbox, *,
                     ca_file: Path | None = None, engine_loop: EngineLoop | None = None, **link_options) -> WardLink:
    """A ward link for ``bed`` of ``ward`` over the hospital engine's nodes at ``urls`` (over TLS trusting the
    hospital CA ``ca_file`` if given; on ``engine_loop``, shared with other beds, if given); ``link_options`` are
    :class:`~appliance.alerts.wardlink.WardLink`'s (``confirm``, ``confirm_timeout_s``, ...)."""
    return WardLink(EngineTransport(urls, ward, bed, password, ca_file=ca_file, engine_loop=engine_loop), bed, outbox,
                    **link_options)
