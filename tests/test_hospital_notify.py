"""The notification service on a real three-node engine, paging to a gateway on loopback: each alarm change of
its priorities POSTed once with its idempotency key and recorded on the engine, turns and low alarms not paged;
a gateway down held as a technical alarm and every page delivered once it is back; a page journalled but not
recorded not posted again after a restart; a service killed mid-stream posting nothing twice but the page in
flight; a page refused for good recorded and not tried again; each outcome shown with its alarm at the ward
station, again after the station's restart and once however often it comes; the ward screen told when pages do
not go out and when the service went quiet; a gateway that dies while no page is due found by a probe; the
service's and the station's users held to their own ward's records and status; the description's [[notifier]]
tables checked."""

import asyncio
import contextlib
import dataclasses
import http.server
import json
import logging
import re
import signal
import subprocess
import sys
import threading
import time
import tomllib
from collections import Counter

import nats.js.errors
import pytest
from hospital_engine import Refusals, WARDS, logged_in, make_streams, running_cluster
from mqtt_broker import wait_until
from test_ward_screen import ward, ward_app
from webui_client import client_as

from appliance.alerts.events import Event
from appliance.errors import ConfigError
from appliance.hospital.description import Notifier, description_text, hospital_from_mapping
from appliance.hospital.engine import BedPublisher, confirms_stream_config
from appliance.hospital.nodeconfig import ADMIN, notifier_permissions, read_password, write_node_configs
from appliance.hospital.notify import IDEMPOTENCY_KEY, GatewayUnavailable, NotificationService, probe_gateway
from appliance.hospital.subjects import (bed_subject, confirmation_subject, confirms_stream_name, notified_subject,
                                         paging_status_subject, stream_name)
from appliance.ward.applied import AppliedJournal
from appliance.ward.board import PAGING_FIRST_WORD_S, STALE_MARGIN_S, WardBoard
from appliance.ward.engine_station import EngineStation

WAIT_S = 90.0               # generous: a redelivery comes after the consumer's acknowledgement wait, on a busy machine
USER = "notify-phones"
STREAM_ATTEMPTS = 3


class Gateway:
    """A messaging gateway on loopback: each POST is kept (its idempotency key, the status answered, its body)
    before it is answered with ``answer(body)``, after ``delay_s``; a HEAD or GET (a probe) is kept as (method, path)
    and answered ``probe_answer(method, path)``."""

    def __init__(self):
        self.pages: list[tuple[str, int, dict]] = []
        self.probes: list[tuple[str, str]] = []
        self.answer = lambda body: 200
        self.probe_answer = lambda method, path: 405 if method == "HEAD" else 200
        self.delay_s = 0.0
        self._lock = threading.Lock()
        gateway = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_POST(self):
                body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
                status = gateway.answer(body)
                with gateway._lock:
                    gateway.pages.append((self.headers[IDEMPOTENCY_KEY], status, body))
                time.sleep(gateway.delay_s)
                self.send_response(status)
                self.send_header("Content-Length", "0")
                self.end_headers()

            def do_HEAD(self):
                self._probed()

            def do_GET(self):
                self._probed()

            def _probed(self):
                with gateway._lock:
                    gateway.probes.append((self.command, self.path))
                self.send_response(gateway.probe_answer(self.command, self.path))
                self.send_header("Content-Length", "0")
                self.end_headers()

            def log_message(self, *args):
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.server.server_address[1]}/pages"

    def keys(self, status: int | None = None) -> list[str]:
        with self._lock:
            return [key for key, answered, _ in self.pages if status is None or answered == status]

    def close(self):
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def gateway():
    running = Gateway()
    yield running
    running.close()


@pytest.fixture
def cluster(tmp_path, gateway):
    with running_cluster(tmp_path, [Notifier("phones", ("ward1",), gateway.url)]) as running:
        for attempt in range(STREAM_ATTEMPTS):
            try:
                asyncio.run(make_streams(running))
                break
            except TimeoutError:            # the nodes may still be electing their leader on a busy machine
                if attempt == STREAM_ATTEMPTS - 1:
                    raise
        yield running


def alarm(kind, priority="high", alarm_id=1):
    return Event(time_s=100.0, type="alarm", kind=kind, priority=priority, category="clinical",
                 key="pressure:sacrum", site="sacrum", alarm_id=alarm_id, message="Sacrum dose over limit").to_dict()


def turn():
    return Event(time_s=100.0, type="turn", kind="repositioned", posture="left", message="repositioned").to_dict()


@contextlib.asynccontextmanager
async def running_service(cluster, folder, **options):
    """The service of the cluster's notifier in this loop, its journal in ``folder``; stopped when the block ends."""
    journal = AppliedJournal(folder / "notify.db")
    try:
        async with logged_in(cluster, USER) as connection:
            service = NotificationService(connection, cluster.hospital.notifier("phones"), journal, **options)
            running = asyncio.create_task(service.run())
            try:
                yield service
            finally:
                service.stop()
                await running
    finally:
        journal.close()


async def send(cluster, bed, events):
    """``bed`` of ward1 sends ``events``, (kind, event) pairs numbered from 1, each until acknowledged."""
    async with logged_in(cluster, bed) as connection:
        publisher = BedPublisher(connection, "ward1", bed)
        for seq, (kind, event) in enumerate(events, start=1):
            await publisher.send(kind, seq, event)


async def records(admin, bed, seqs) -> dict[int, dict]:
    """The service's records of ``bed``'s events ``seqs`` that the confirmation stream holds."""
    found = {}
    for seq in seqs:
        with contextlib.suppress(nats.js.errors.NotFoundError):
            message = await admin.jetstream().get_last_msg(confirms_stream_name("ward1"),
                                                           notified_subject("ward1", bed, seq, "phones"))
            found[seq] = json.loads(message.data)
    return found


async def recorded(cluster, bed, seqs) -> dict[int, dict]:
    """Wait until the confirmation stream holds a record of each of ``seqs``, and those records."""
    async with logged_in(cluster, ADMIN) as admin:
        give_up = asyncio.get_running_loop().time() + WAIT_S
        while len(found := await records(admin, bed, seqs)) < len(seqs):
            assert asyncio.get_running_loop().time() < give_up, f"records of {sorted(found)} only, of {seqs}"
            await asyncio.sleep(0.2)
        return found


async def wait_acknowledged(cluster) -> None:
    """Wait until the service's consumer has every event of ward1's stream acknowledged."""
    async with logged_in(cluster, ADMIN) as admin:
        give_up = asyncio.get_running_loop().time() + WAIT_S
        while True:
            info = await admin.jetstream().consumer_info(stream_name("ward1"), USER)
            if info.num_pending == 0 and info.num_ack_pending == 0:
                return
            assert asyncio.get_running_loop().time() < give_up, f"not all acknowledged: {info}"
            await asyncio.sleep(0.2)


def ward1_station(cluster, path):
    """Station1 of ward1 on the cluster, its journal at ``path``, reading its ward."""
    station = EngineStation(cluster.urls, "ward1", "station1", read_password(cluster.configs.secrets_folder,
                                                                             "station1"), AppliedJournal(path))
    assert station.wait_subscribed(WAIT_S)
    return station


def close(station):
    station.close()
    station.journal.close()


def shown_pages(station, bed="bed1"):
    """What ``station`` shows of ``bed``'s open alarms' pages: alarm id -> [(service, outcome, status, time)]."""
    alarms = next((b["alarms"] for b in station.beds(events=False) if b["bed_id"] == bed), [])
    return {a["alarm_id"]: [(p["notifier"], p["outcome"], p["status"], p["notified_at"]) for p in a["pages"]]
            for a in alarms}


async def until(condition, what):
    give_up = asyncio.get_running_loop().time() + WAIT_S
    while not condition():
        assert asyncio.get_running_loop().time() < give_up, f"never: {what}"
        await asyncio.sleep(0.1)


def test_each_alarm_change_of_its_priorities_is_paged_once_and_recorded_and_nothing_else(cluster, gateway, tmp_path):
    async def run():
        async with running_service(cluster, tmp_path) as service:
            await send(cluster, "bed1", [("alarm", alarm("raised")), ("turn", turn()),
                                         ("alarm", alarm("acknowledged")), ("alarm", alarm("raised", "low", 2)),
                                         ("alarm", alarm("ended", "medium", 3)),
                                         ("episode", Event(time_s=1.0, type="episode", kind="admitted").to_dict())])
            found = await recorded(cluster, "bed1", [1, 3, 5])
            await wait_acknowledged(cluster)
            return service, found

    service, found = asyncio.run(run())
    assert gateway.keys() == ["bed1:1", "bed1:3", "bed1:5"]
    assert [(body["bed_id"], body["seq"], body["ward"], body["kind"], body["priority"])
            for _, _, body in gateway.pages] == [("bed1", 1, "ward1", "raised", "high"),
                                                 ("bed1", 3, "ward1", "acknowledged", "high"),
                                                 ("bed1", 5, "ward1", "ended", "medium")]
    assert {seq: (r["outcome"], r["status"], r["notifier"], r["alarm_id"]) for seq, r in found.items()} == {
        1: ("paged", 200, "phones", 1), 3: ("paged", 200, "phones", 1), 5: ("paged", 200, "phones", 3)}
    assert (service.paged, service.refused, service.failures) == (3, 0, 0)
    assert service.conditions() == {}


def test_a_gateway_down_is_a_condition_and_every_page_goes_once_it_is_back(cluster, gateway, tmp_path, caplog):
    gateway.answer = lambda body: 503

    async def run():
        async with running_service(cluster, tmp_path) as service:
            await send(cluster, "bed1", [("alarm", alarm("raised", alarm_id=n)) for n in (1, 2, 3)])
            await until(lambda: len(gateway.keys(503)) >= 2 and service.conditions(), "two tries refused")
            raised = service.conditions()
            async with logged_in(cluster, ADMIN) as admin:
                held = await records(admin, "bed1", [1, 2, 3])
            gateway.answer = lambda body: 200
            found = await recorded(cluster, "bed1", [1, 2, 3])
            await wait_acknowledged(cluster)
            return service, raised, held, found

    with caplog.at_level(logging.WARNING, logger="appliance.hospital.notify"):
        service, raised, held, found = asyncio.run(run())
    assert list(raised) == [f"technical:{USER}"] and "(HTTP 503)" in raised[f"technical:{USER}"]
    assert held == {}                                   # nothing recorded while the gateway took nothing
    assert sorted(gateway.keys(200)) == ["bed1:1", "bed1:2", "bed1:3"]
    assert set(gateway.keys(503)) <= {"bed1:1", "bed1:2", "bed1:3"}
    assert service.failures == len(gateway.keys(503)) >= 2
    assert all(record["outcome"] == "paged" for record in found.values())
    assert service.conditions() == {}
    said = [r.getMessage() for r in caplog.records]
    assert len([m for m in said if "takes no pages" in m]) == 1              # once per outage, not per try
    assert len([m for m in said if "takes pages again" in m]) == 1


def test_a_page_refused_for_good_is_recorded_not_tried_again_and_each_outcome_shown_at_the_station(cluster, gateway,
                                                                                                    tmp_path):
    gateway.answer = lambda body: 422 if body["seq"] == 2 else 200
    station = EngineStation(cluster.urls, "ward1", "station1", read_password(cluster.configs.secrets_folder,
                                                                             "station1"),
                            AppliedJournal(tmp_path / "station.db"))

    def pages():
        alarms = next((bed["alarms"] for bed in station.beds(events=False) if bed["bed_id"] == "bed1"), [])
        return {a["alarm_id"]: [(p["notifier"], p["outcome"], p["status"]) for p in a["pages"]] for a in alarms}

    async def run():
        async with running_service(cluster, tmp_path) as service:
            await send(cluster, "bed1", [("alarm", alarm("raised", alarm_id=n)) for n in (1, 2, 3)])
            found = await recorded(cluster, "bed1", [1, 2, 3])
            await wait_acknowledged(cluster)
            await until(lambda: all(pages().get(n) for n in (1, 2, 3)), "the station shows every page")
            return service, found

    try:
        assert station.wait_subscribed(WAIT_S)
        service, found = asyncio.run(run())
        shown = pages()
    finally:
        station.close()
        station.journal.close()
    assert gateway.keys() == ["bed1:1", "bed1:2", "bed1:3"]          # the refused one once, acknowledged
    assert [(found[seq]["outcome"], found[seq]["status"]) for seq in (1, 2, 3)] == [
        ("paged", 200), ("refused", 422), ("paged", 200)]
    assert (service.paged, service.refused) == (2, 1)
    assert service.conditions() == {}                  # the gateway answered: it is not down
    assert shown == {1: [("phones", "paged", 200)], 2: [("phones", "refused", 422)], 3: [("phones", "paged", 200)]}


def test_the_board_keeps_each_alarms_latest_page_and_refuses_a_bad_record():
    board = WardBoard()
    board.take("bed1", "alarm", json.dumps({**alarm("raised"), "bed_id": "bed1", "seq": 1}).encode())

    def record(seq, outcome="paged", bed="bed1"):
        return json.dumps({"bed_id": bed, "seq": seq, "notifier": "phones", "outcome": outcome, "status": 200,
                           "alarm_id": 1, "kind": "raised", "notified_at": 1.0e9}).encode()

    assert board.take_page("bed1", record(3))["seq"] == 3
    board.take_page("bed1", record(2, "refused"))                   # older than the one kept: changes nothing
    assert board.take_page("bed1", record(4, bed="bed2")) is None   # not this bed's
    assert board.take_page("bed1", b"[]") is None
    assert [a["pages"] for a in board.beds()[0]["alarms"]] == [
        [{"notifier": "phones", "outcome": "paged", "status": 200, "notified_at": 1.0e9}]]
    assert board.bad_payloads == 2


def test_a_page_the_engine_could_not_record_is_not_posted_again_by_the_service_started_again(cluster, gateway,
                                                                                             tmp_path):
    """The confirmation stream made to take no records while the service pages: the page is journalled but its
    event not acknowledged; the service started again finds it in its journal, records it and posts nothing."""
    async def run():
        async with logged_in(cluster, ADMIN) as admin:
            js = admin.jetstream()
            config = confirms_stream_config(cluster.hospital.wards[0], cluster.hospital.replicas)
            await js.update_stream(dataclasses.replace(config, subjects=config.subjects[:1]))
            async with running_service(cluster, tmp_path) as first:
                await send(cluster, "bed1", [("alarm", alarm("raised"))])
                await until(lambda: first.paged == 1, "the page taken by the gateway")
            await js.update_stream(config)
            async with running_service(cluster, tmp_path) as again:
                found = await recorded(cluster, "bed1", [1])
                await wait_acknowledged(cluster)
                return again, found

    again, found = asyncio.run(run())
    assert gateway.keys() == ["bed1:1"]
    assert (again.paged, again.repeats) == (0, 1) and found[1]["outcome"] == "paged"


def test_a_service_killed_mid_stream_pages_nothing_twice_but_the_one_in_flight(cluster, gateway, tmp_path):
    """``appliance hospital notify`` as a process, SIGKILLed while it pages 30 alarm changes, then started
    again on the same journal: the gateway sees every key, and at most one (the page in flight) twice."""
    total = 30
    gateway.delay_s = 0.1
    description = tmp_path / "hospital.toml"
    description.write_text(description_text(cluster.hospital))
    command = [sys.executable, "-m", "appliance", "hospital", "notify", "--description", str(description),
               "--secrets", str(cluster.configs.secrets_folder), "--notifier", "phones",
               "--journal", str(tmp_path / "notify.db")]
    asyncio.run(send(cluster, "bed1", [("alarm", alarm("raised", alarm_id=n)) for n in range(1, total + 1)]))
    first = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL)
    try:
        assert wait_until(lambda: len(gateway.keys()) >= 10, WAIT_S)
    finally:
        first.send_signal(signal.SIGKILL)
        first.wait(10)
    killed_at = len(gateway.keys())
    second = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                              text=True)
    try:
        found = asyncio.run(recorded(cluster, "bed1", list(range(1, total + 1))))
        asyncio.run(wait_acknowledged(cluster))
    finally:
        second.send_signal(signal.SIGTERM)
        out, _ = second.communicate(timeout=30)
    assert second.returncode == 0, out
    assert killed_at < total
    seen = Counter(gateway.keys())
    assert set(seen) == {f"bed1:{seq}" for seq in range(1, total + 1)}
    assert max(seen.values()) <= 2 and sum(count == 2 for count in seen.values()) <= 1, seen
    assert all(record["outcome"] == "paged" for record in found.values()) and len(found) == total
    assert "notification service phones stopped" in out


def test_the_services_user_records_only_its_own_and_no_one_else_records_for_it(cluster):
    refused = Refusals(USER, "station1", "bed1")

    async def run():
        async with logged_in(cluster, USER, on_error=refused.note(USER)) as service, \
                logged_in(cluster, "station1", on_error=refused.note("station1")) as station, \
                logged_in(cluster, "bed1", on_error=refused.note("bed1")) as bed:
            await service.publish(bed_subject("ward1", "bed1", "alarm"), b"{}")
            await service.publish(confirmation_subject("ward1", "bed1", 1), b"{}")
            await service.publish(notified_subject("ward2", "bed3", 1, "phones"), b"{}")    # not its ward
            await service.publish(notified_subject("ward1", "bed1", 1, "pagers"), b"{}")    # not its name
            await service.subscribe(bed_subject("ward1", "*", "alarm"))
            await station.publish(notified_subject("ward1", "bed1", 1, "phones"), b"{}")
            await bed.publish(notified_subject("ward1", "bed1", 1, "phones"), b"{}")
            await until(lambda: len(refused[USER]) >= 5 and refused["station1"] and refused["bed1"], "refusals")
            own = await service.jetstream().publish(notified_subject("ward1", "bed1", 1, "phones"), b"{}",
                                                    stream=confirms_stream_name("ward1"))
            return own

    own = asyncio.run(run())
    assert sorted(refused[USER]) == [
        'nats: permissions violation for publish to "hospital.ward1.bed1.alarm"',
        'nats: permissions violation for publish to "hospital.ward1.bed1.confirmed.1"',
        'nats: permissions violation for publish to "hospital.ward1.bed1.notified.1.pagers"',
        'nats: permissions violation for publish to "hospital.ward2.bed3.notified.1.phones"',
        'nats: permissions violation for subscription to "hospital.ward1.*.alarm"']
    assert refused["station1"] == ['nats: permissions violation for publish to "hospital.ward1.bed1.notified.1.phones"']
    assert refused["bed1"] == ['nats: permissions violation for publish to "hospital.ward1.bed1.notified.1.phones"']
    assert own.stream == "CONFIRMS_ward1"


def test_a_restarted_station_reads_the_pages_back_and_shows_each_once(cluster, gateway, tmp_path):
    """Two alarms paged (one refused) while the station runs, a third while it is closed; the station started
    again on its journal shows all three pages as before, and a record given again (a service's repeat) once."""
    gateway.answer = lambda body: 422 if body["seq"] == 2 else 200
    journal = tmp_path / "station.db"

    async def run():
        async with running_service(cluster, tmp_path):
            first = ward1_station(cluster, journal)
            try:
                await send(cluster, "bed1", [("alarm", alarm("raised", alarm_id=n)) for n in (1, 2)])
                await until(lambda: all(shown_pages(first).get(n) for n in (1, 2)), "the running station shows both")
                before = shown_pages(first)
            finally:
                close(first)
            async with logged_in(cluster, "bed1") as connection:
                await BedPublisher(connection, "ward1", "bed1").send("alarm", 3, alarm("raised", alarm_id=3))
            stored_while_closed = await recorded(cluster, "bed1", [3])
        again = ward1_station(cluster, journal)
        try:
            await until(lambda: all(shown_pages(again).get(n) for n in (1, 2, 3)), "the restarted station shows all")
            after = shown_pages(again)
            async with logged_in(cluster, ADMIN) as admin:
                kept = await admin.jetstream().get_last_msg(confirms_stream_name("ward1"),
                                                            notified_subject("ward1", "bed1", 1, "phones"))
            version = again.version
            async with logged_in(cluster, USER) as service:           # the service's record of event 1, again
                await service.jetstream().publish(kept.subject, kept.data, stream=confirms_stream_name("ward1"))
            await until(lambda: again.version > version, "the repeat heard")
            return before, stored_while_closed, after, shown_pages(again)
        finally:
            close(again)

    before, stored_while_closed, after, repeated = asyncio.run(run())
    assert {n: [(p[0], p[1], p[2]) for p in pages] for n, pages in before.items()} == {
        1: [("phones", "paged", 200)], 2: [("phones", "refused", 422)]}
    assert after == {**before, 3: [("phones", "paged", 200, stored_while_closed[3]["notified_at"])]}
    assert repeated == after                                  # one page line per alarm and service


def test_the_ward_screen_says_while_pages_do_not_go_out_and_when_the_service_went_quiet(cluster, gateway, tmp_path):
    """The gateway answers 503: the service says so to the ward, and the screen's JSON shows it not delivering
    (a station started afresh too, within the service's period); once the gateway takes pages, delivering; the
    service stopped, unknown after a few of its periods, never delivering."""
    gateway.answer = lambda body: 503
    every_s = 0.5
    (tmp_path / "screen").mkdir()

    def paging(station):
        return {s["notifier"]: (s["state"], s["reason"]) for s in station.paging()}

    async def run():
        station = ward1_station(cluster, tmp_path / "station.db")
        try:
            nurse = client_as(ward_app(tmp_path / "screen", station), "nurse")
            async with running_service(cluster, tmp_path, status_every_s=every_s) as service:
                await until(lambda: paging(station) == {"phones": ("delivering", "")}, "the service heard")
                await send(cluster, "bed1", [("alarm", alarm("raised"))])
                await until(lambda: paging(station) == {"phones": ("not delivering", "HTTP 503")}, "not delivering")
                failing = ward(nurse)["paging"]
                fresh = ward1_station(cluster, tmp_path / "fresh.db")
                try:
                    await until(lambda: paging(fresh) == {"phones": ("not delivering", "HTTP 503")},
                                "a station started afresh told")
                finally:
                    close(fresh)
                gateway.answer = lambda body: 200
                await until(lambda: paging(station) == {"phones": ("delivering", "")}, "delivering again")
                await until(lambda: service.paged == 1, "the page taken")
                recovered = ward(nurse)["paging"]
            await until(lambda: paging(station)["phones"][0] == "unknown", "the silent service shown unknown")
            quiet = ward(nurse)["paging"]
            return failing, recovered, quiet
        finally:
            close(station)

    failing, recovered, quiet = asyncio.run(run())
    assert [(s["notifier"], s["state"], s["reason"]) for s in failing] == [("phones", "not delivering", "HTTP 503")]
    assert recovered[0]["since"] != failing[0]["since"]              # each change of state dated anew
    assert [(s["notifier"], s["state"]) for s in recovered] == [("phones", "delivering")]
    assert [(s["notifier"], s["state"]) for s in quiet] == [("phones", "unknown")]
    assert quiet[0]["since"] == quiet[0]["heard_at"]          # when it was last heard


def test_a_probe_passes_a_gateway_that_answers_and_names_why_one_fails(gateway):
    page_address, health = gateway.url, gateway.url.replace("/pages", "/health")
    probe_gateway(page_address, False, 5.0)                    # HEAD answered 405: a server is there
    probe_gateway(health, True, 5.0)                           # the health address answered 200
    gateway.probe_answer = lambda method, path: 503 if method == "HEAD" else 404
    for url, asks_health, why in ((page_address, False, "HTTP 503 to a probe"), (health, True, "HTTP 404 to a probe")):
        with pytest.raises(GatewayUnavailable, match=why):
            probe_gateway(url, asks_health, 5.0)
    assert gateway.probes == [("HEAD", "/pages"), ("GET", "/health"), ("HEAD", "/pages"), ("GET", "/health")]
    gateway.close()
    with pytest.raises(GatewayUnavailable, match="no answer to a probe"):
        probe_gateway(page_address, False, 5.0)


def test_a_gateway_that_dies_while_no_page_is_due_is_shown_before_the_next_alarm(cluster, gateway, tmp_path):
    """No alarm comes; the gateway's probes fail: the service earns its technical alarm and the station shows pages
    not going out, with no page tried; the probes pass again: delivering. An outage a page found is not ended by a
    probe: only a page taken ends it."""
    every_s = 0.2

    def paging(station):
        return {s["notifier"]: (s["state"], s["reason"]) for s in station.paging()}

    async def run():
        station = ward1_station(cluster, tmp_path / "station.db")
        try:
            async with running_service(cluster, tmp_path, status_every_s=every_s, probe_every_s=every_s) as service:
                await until(lambda: gateway.probes and paging(station) == {"phones": ("delivering", "")},
                            "probed, and delivering")
                gateway.probe_answer = lambda method, path: 503
                await until(lambda: paging(station) == {"phones": ("not delivering", "HTTP 503 to a probe")},
                            "the dead gateway shown")
                condition = dict(service.conditions())
                gateway.probe_answer = lambda method, path: 405
                await until(lambda: paging(station) == {"phones": ("delivering", "")}, "delivering again")
                gateway.answer = lambda body: 503
                await send(cluster, "bed1", [("alarm", alarm("raised"))])
                await until(lambda: paging(station) == {"phones": ("not delivering", "HTTP 503")}, "the page refused")
                probes = len(gateway.probes)
                await until(lambda: len(gateway.keys(503)) >= 3, "the page tried again")
                held = (paging(station), dict(service.conditions()), len(gateway.probes) - probes)
                gateway.answer = lambda body: 200
                await until(lambda: service.paged == 1 and paging(station) == {"phones": ("delivering", "")},
                            "the page taken")
                return condition, held
        finally:
            close(station)

    condition, (held_paging, held_condition, probes_while_paging) = asyncio.run(run())
    assert list(condition) == ["technical:notify-phones"]
    assert "answered no probe" in condition["technical:notify-phones"]
    assert "HTTP 503 to a probe" in condition["technical:notify-phones"]
    assert held_paging == {"phones": ("not delivering", "HTTP 503")}        # passing probes did not end it
    assert "taken no page" in held_condition["technical:notify-phones"]
    assert probes_while_paging <= 1                 # pages tried: the gateway is not probed besides (one in flight)
    assert gateway.keys(200) == ["bed1:1"]


def test_the_board_shows_a_service_silent_for_a_few_periods_or_never_heard_as_unknown():
    steady = 1000.0
    board = WardBoard(steady_clock=lambda: steady)                  # the board's clock stands still: no timing

    def status(delivering=False, since=1.0e9, reason="HTTP 503", every_s=5.0, notifier="phones"):
        return json.dumps({"notifier": notifier, "delivering": delivering, "since": since, "reason": reason,
                           "every_s": every_s}).encode()

    assert board.take_paging("phones", status(), now=2.0e9)["delivering"] is False
    version = board.version
    board.take_paging("phones", status(), now=2.0e9 + 5)          # the same word again: nothing changed
    assert board.version == version
    assert [(s["state"], s["since"], s["reason"]) for s in board.paging(steady)] == [
        ("not delivering", 1.0e9, "HTTP 503")]
    later = steady + 3 * 5.0 + STALE_MARGIN_S + 1
    assert [(s["state"], s["since"]) for s in board.paging(later)] == [("unknown", 2.0e9 + 5)]
    board.take_page("bed1", json.dumps({"bed_id": "bed1", "seq": 1, "notifier": "pagers", "outcome": "paged",
                                        "status": 200, "alarm_id": 1, "kind": "raised",
                                        "notified_at": 1.0e9}).encode())
    assert [s["notifier"] for s in board.paging(steady)] == ["phones"]      # pagers not judged yet
    assert [(s["notifier"], s["state"], s["since"]) for s in board.paging(steady + PAGING_FIRST_WORD_S + 1)] == [
        ("pagers", "unknown", None), ("phones", "unknown", 2.0e9 + 5)]
    for bad in (status(notifier="pagers"), status(every_s=0), b'{"notifier": "phones"}', b"[]"):
        assert board.take_paging("phones", bad) is None
    assert board.bad_payloads == 4


def test_a_station_reads_back_and_hears_only_its_own_wards_pages_and_only_the_service_says_its_status(cluster):
    refused = Refusals(USER, "station1", "bed1")

    async def run():
        async with logged_in(cluster, USER, on_error=refused.note(USER)) as service, \
                logged_in(cluster, "station1", on_error=refused.note("station1")) as station, \
                logged_in(cluster, "bed1", on_error=refused.note("bed1")) as bed:
            js = station.jetstream()
            for stream, subject in ((confirms_stream_name("ward2"), notified_subject("ward2", "*", "*", "*")),
                                    (confirms_stream_name("ward1"), f"{bed_subject('ward1', '*', 'confirmed')}.*")):
                with pytest.raises(nats.errors.TimeoutError):     # the engine drops the call: no answer
                    await js.pull_subscribe(subject, stream=stream)
            await station.subscribe(paging_status_subject("ward2", "*"))
            await station.publish(paging_status_subject("ward1", "phones"), b"{}")
            await bed.publish(paging_status_subject("ward1", "phones"), b"{}")
            await service.publish(paging_status_subject("ward2", "phones"), b"{}")    # not its ward
            await service.publish(paging_status_subject("ward1", "pagers"), b"{}")    # not its name
            await until(lambda: len(refused["station1"]) >= 4 and refused["bed1"] and len(refused[USER]) >= 2,
                        "refusals")
            await service.jetstream().publish(notified_subject("ward1", "bed1", 1, "phones"), b"{}",
                                              stream=confirms_stream_name("ward1"))
            own = await js.pull_subscribe(notified_subject("ward1", "*", "*", "*"),
                                          stream=confirms_stream_name("ward1"))
            return [message.subject for message in await own.fetch(1, timeout=WAIT_S)]

    assert asyncio.run(run()) == ["hospital.ward1.bed1.notified.1.phones"]        # its own ward's, read back
    unnamed = sorted(re.sub(r"(create\.confirms_ward\d)\.\w+\.", r"\1.<name>.", error, flags=re.IGNORECASE)
                     for error in refused["station1"])
    assert unnamed == [
        'nats: permissions violation for publish to "$js.api.consumer.create.confirms_ward1.<name>.hospital.ward1.*.'
        'confirmed.*"',
        'nats: permissions violation for publish to "$js.api.consumer.create.confirms_ward2.<name>.hospital.ward2.*.'
        'notified.*.*"',
        'nats: permissions violation for publish to "hospital.ward1.paging.status.phones"',
        'nats: permissions violation for subscription to "hospital.ward2.paging.status.*"']
    assert refused["bed1"] == ['nats: permissions violation for publish to "hospital.ward1.paging.status.phones"']
    assert sorted(refused[USER]) == [
        'nats: permissions violation for publish to "hospital.ward1.paging.status.pagers"',
        'nats: permissions violation for publish to "hospital.ward2.paging.status.phones"']


DESCRIBED = {"hospital": {"cluster": "st-mary", "store_dir": "/var/lib/h"},
             "node": [{"name": "n1", "host": "127.0.0.1"}], "ward": [{"name": w.name, "beds": list(w.beds),
                                                                      "stations": list(w.stations)} for w in WARDS]}


def described(**notifier):
    return {**DESCRIBED, "hospital": {**DESCRIBED["hospital"], "replicas": 1},
            "notifier": [{"name": "phones", "wards": ["ward1"], "url": "https://pager.example/pages", **notifier}]}


def test_a_notifier_is_described_with_its_defaults_and_written_back_the_same(tmp_path):
    hospital = hospital_from_mapping(described())
    assert hospital.notifiers == (Notifier("phones", ("ward1",), "https://pager.example/pages", ("high", "medium")),)
    assert hospital_from_mapping(tomllib.loads(description_text(hospital))) == hospital
    assert hospital_from_mapping(described(priorities=["low"])).notifier("phones").priorities == ("low",)
    probed = hospital_from_mapping(described(probe_url="https://pager.example/health"))
    assert probed.notifier("phones").probe_url == "https://pager.example/health"
    assert hospital_from_mapping(tomllib.loads(description_text(probed))) == probed
    written = write_node_configs(hospital, tmp_path / "out")
    assert USER in written.added
    assert notifier_permissions(hospital.notifier("phones"))["publish"]["allow"][-2:] == \
        ["hospital.ward1.*.notified.*.phones", "hospital.ward1.paging.status.phones"]
    with pytest.raises(ConfigError, match="no \\[\\[notifier\\]\\] named 'pagers'.*its notifiers: phones"):
        hospital.notifier("pagers")


@pytest.mark.parametrize("notifier, message", [
    ({"name": "pho nes"}, "[[notifier]] number 1 name 'pho nes'"),
    ({"wards": ["ward9"]}, "[[notifier]] phones wards: 'ward9' is not a [[ward]] of the hospital; its wards: ward1, "
                           "ward2"),
    ({"wards": []}, "[[notifier]] phones: 'wards' must be a non-empty list"),
    ({"url": "ftp://pager.example/"}, "[[notifier]] phones url 'ftp://pager.example/': must be an http:// or "
                                      "https:// address with a host"),
    ({"url": "https:///pages"}, "must be an http:// or https:// address with a host"),
    ({"probe_url": "pager.example/health"}, "[[notifier]] phones probe_url 'pager.example/health': must be an "
                                            "http:// or https:// address with a host"),
    ({"priorities": ["urgent"]}, "[[notifier]] phones priorities must be a non-empty list of low, medium, high, got "
                                 "['urgent']"),
    ({"priorities": ["high", "high"]}, "[[notifier]] phones priority 'high' is given twice"),
    ({"retries": 3}, "[[notifier]] number 1: unknown key 'retries'"),
])
def test_a_bad_notifier_is_refused_naming_the_key(notifier, message):
    with pytest.raises(ConfigError) as raised:
        hospital_from_mapping(described(**notifier))
    assert message in str(raised.value)


def test_a_bed_cannot_take_a_notification_services_user_name(tmp_path):
    data = described()
    data["ward"] = [{"name": "ward1", "beds": [USER], "stations": ["s1"]}]
    with pytest.raises(ConfigError, match=f"'{USER}' is notification service phones's user"):
        write_node_configs(hospital_from_mapping(data), tmp_path / "out")
