"""The hospital engine on a real three-node cluster: replicated streams, a bed's alarm read by its station,
no acknowledged alarm lost when the stream's leader is killed, and each bed held to its own subjects."""

import asyncio

import nats.errors
import pytest
from hospital_engine import logged_in, make_streams, running_cluster

import nats.js.errors

from appliance.hospital.description import hospital_from_mapping
from appliance.hospital.engine import (KEPT_PER_BED, BedPublisher, Delivery, MemoryLedger, WardReader,
                                      ensure_ward_streams)
from appliance.hospital.nodeconfig import ADMIN
from appliance.hospital.subjects import confirms_stream_name, stream_name


@pytest.fixture
def cluster(tmp_path):
    with running_cluster(tmp_path) as running:
        yield running


def test_the_cluster_forms_and_each_ward_stream_has_three_replicas_on_fsynced_nodes(cluster):
    assert asyncio.run(make_streams(cluster)) == ["ALARMS_ward1", "CONFIRMS_ward1", "ALARMS_ward2", "CONFIRMS_ward2"]
    for node in cluster.hospital.nodes:
        varz = cluster.monitor(node.name, "varz")
        assert varz["version"] == "2.15.1"
        assert varz["jetstream"]["config"]["sync_always"] is True
        assert varz["jetstream"]["meta"]["cluster_size"] == 3

    async def replicas():
        async with logged_in(cluster, ADMIN) as admin:
            info = await admin.jetstream().stream_info("ALARMS_ward1")
        return info.config.num_replicas, info.cluster.leader, sorted(peer.name for peer in info.cluster.replicas)

    count, leader, followers = asyncio.run(replicas())
    assert count == 3
    assert sorted([leader, *followers]) == ["n1", "n2", "n3"]


def test_an_acknowledged_alarm_reaches_its_ward_station_once_even_when_resent(cluster):
    asyncio.run(make_streams(cluster))

    async def run():
        async with logged_in(cluster, "bed1") as bed, logged_in(cluster, "station1") as station:
            publisher = BedPublisher(bed, "ward1", "bed1")
            first = await publisher.send("alarm", 1, {"kind": "sacrum", "priority": "high"})
            again = await publisher.send("alarm", 1, {"kind": "sacrum", "priority": "high"})
            reader = WardReader(station, "ward1", "station1")
            return first, again, await reader.read(timeout_s=2), reader

    first, again, deliveries, reader = asyncio.run(run())
    assert first.stream == "ALARMS_ward1" and not first.duplicate
    assert again.duplicate and again.seq == first.seq          # the resend was not stored twice
    assert [(d.bed, d.seq, d.kind, d.event["kind"]) for d in deliveries] == [("bed1", 1, "alarm", "sacrum")]
    assert reader.delivered == 1


def test_killing_the_stream_leader_under_load_loses_no_acknowledged_alarm(cluster):
    """200 alarms published one after the other, each until acknowledged; the stream's leader is SIGKILLed
    after the 50th. Every acknowledged alarm is in the stream once and the station applies each once."""
    asyncio.run(make_streams(cluster))
    total, kill_after = 200, 50

    async def run():
        async with logged_in(cluster, ADMIN) as admin, logged_in(cluster, "bed1") as bed:
            js = admin.jetstream()
            publisher = BedPublisher(bed, "ward1", "bed1")
            acknowledged, halfway = [], asyncio.Event()

            async def kill_leader():                           # while the bed goes on publishing
                await halfway.wait()
                leader = (await js.stream_info(stream_name("ward1"))).cluster.leader
                await asyncio.to_thread(cluster.kill, leader)
                return leader

            killer = asyncio.create_task(kill_leader())
            for seq in range(1, total + 1):
                ack = await publisher.send("alarm", seq, {"kind": "heel", "n": seq}, deadline_s=45)
                assert ack.stream == "ALARMS_ward1"
                acknowledged.append(seq)
                if seq == kill_after:
                    halfway.set()
            killed = await killer
            info = await js.stream_info(stream_name("ward1"))
        async with logged_in(cluster, "station1") as station:
            reader = WardReader(station, "ward1", "station1")
            seen, give_up = [], asyncio.get_running_loop().time() + 40
            while len(seen) < total and asyncio.get_running_loop().time() < give_up:
                seen += await reader.read(batch=100, timeout_s=1)
        return acknowledged, killed, info, reader, seen

    acknowledged, killed, info, reader, seen = asyncio.run(run())
    assert killed in {"n1", "n2", "n3"} and not cluster.running(killed)
    assert info.cluster.leader != killed                       # a new leader took over
    assert acknowledged == list(range(1, total + 1))
    assert info.state.messages == total                        # resends across the kill were not stored twice
    assert [d.seq for d in seen] == acknowledged               # every acknowledged alarm, once, in order
    assert reader.duplicates == reader.delivered - total and {d.bed for d in seen} == {"bed1"}
    assert all(d.event["n"] == d.seq for d in seen)


def test_a_memory_ledger_takes_each_number_once_and_stays_bounded_however_long_it_runs():
    ledger = MemoryLedger()
    numbers = list(range(1, 3 * KEPT_PER_BED + 1))
    numbers[10:12] = [12, 11]                                       # a resend stored after the next number
    assert all(ledger.take(Delivery("bed1", n, "alarm", {})) for n in numbers)
    assert ledger.take(Delivery("bed2", 5, "alarm", {}))            # each bed its own numbers
    assert not ledger.take(Delivery("bed1", 3 * KEPT_PER_BED, "alarm", {}))         # taken before
    assert not ledger.take(Delivery("bed1", KEPT_PER_BED, "alarm", {}))             # too far behind: taken
    assert ledger.take(Delivery("bed1", 3 * KEPT_PER_BED + 1, "alarm", {}))
    assert len(ledger) <= 2 * KEPT_PER_BED + 2                      # not the 30,000 numbers taken


class ElectingJetStream:
    """A JetStream API that leaves its first ``unanswered`` calls (of kind ``only``, if given) unanswered: they time
    out, then it answers. A stream creation that times out was made all the same, as a lost answer leaves it."""

    def __init__(self, unanswered: int, only: str | None = None):
        self.unanswered, self.only, self.streams, self.calls = unanswered, only, set(), []

    async def _call(self, what: str, name: str):
        self.calls.append((what, name))
        if self.unanswered and self.only in (None, what):
            self.unanswered -= 1
            if what == "add":
                self.streams.add(name)
            raise nats.errors.TimeoutError

    async def stream_info(self, name):
        await self._call("info", name)
        if name not in self.streams:
            raise nats.js.errors.NotFoundError

    async def add_stream(self, config):
        await self._call("add", config.name)
        self.streams.add(config.name)

    async def update_stream(self, config):
        await self._call("update", config.name)


class StubConnection:
    def __init__(self, js):
        self.js = js

    def jetstream(self):
        return self.js


def test_making_the_streams_waits_out_a_cluster_electing_its_leaders_and_gives_up_after_its_time():
    hospital = hospital_from_mapping({"hospital": {"cluster": "c", "store_dir": "/var/lib/h", "replicas": 1},
                                      "node": [{"name": "n1", "host": "127.0.0.1"}],
                                      "ward": [{"name": "ward1", "beds": ["bed1"], "stations": ["station1"]}]})
    electing = ElectingJetStream(unanswered=3)
    names = asyncio.run(ensure_ward_streams(StubConnection(electing), hospital))
    assert names == [stream_name("ward1"), confirms_stream_name("ward1")] and electing.streams == set(names)
    assert electing.calls[:5] == [("info", names[0]), ("info", names[0]), ("info", names[0]), ("info", names[0]),
                                  ("add", names[0])]
    lost = ElectingJetStream(unanswered=1, only="add")                # made, but its answer lost
    asyncio.run(ensure_ward_streams(StubConnection(lost), hospital))
    assert lost.calls[:4] == [("info", names[0]), ("add", names[0]), ("info", names[0]), ("update", names[0])]
    with pytest.raises(nats.errors.TimeoutError):
        asyncio.run(ensure_ward_streams(StubConnection(ElectingJetStream(unanswered=10**6)), hospital, wait_s=0.5))


def test_a_bed_cannot_publish_on_another_beds_subject(cluster):
    asyncio.run(make_streams(cluster))

    async def run():
        errors = []

        async def on_error(error):
            errors.append(str(error))

        async with logged_in(cluster, "bed1", on_error=on_error) as bed, logged_in(cluster, ADMIN) as admin:
            with pytest.raises(TimeoutError, match="not acknowledged"):
                await BedPublisher(bed, "ward1", "bed2").send("alarm", 1, {"kind": "forged"}, deadline_s=1)
            with pytest.raises(TimeoutError, match="not acknowledged"):
                await BedPublisher(bed, "ward2", "bed3").send("alarm", 1, {"kind": "forged"}, deadline_s=1)
            own = await BedPublisher(bed, "ward1", "bed1").send("alarm", 1, {"kind": "sacrum"})
            stored = [(await admin.jetstream().stream_info(stream_name(w))).state.messages for w in ("ward1", "ward2")]
            with pytest.raises(nats.errors.TimeoutError):          # a bed cannot read another bed's confirmations
                sub = await bed.subscribe("hospital.ward1.bed2.confirm")
                await sub.next_msg(timeout=0.5)
        return errors, own, stored

    errors, own, stored = asyncio.run(run())
    assert own.seq == 1 and stored == [1, 0]                    # only its own alarm went in
    assert any('publish to "hospital.ward1.bed2.alarm"' in error for error in errors)
    assert any('publish to "hospital.ward2.bed3.alarm"' in error for error in errors)
    assert any('subscription to "hospital.ward1.bed2.confirm"' in error for error in errors)
