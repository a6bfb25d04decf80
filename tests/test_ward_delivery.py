"""No alarm lost on the way to the ward: the real monitor process killed with SIGKILL 20 times through a
night while the ward's broker (a real Mosquitto that keeps nothing across a restart) is stopped and started
under it, and a real ward station confirms what it shows. Every event the monitor committed must end
confirmed by the station, each under one number, and the station must show the alarms the bed has open."""

import json
import os
import signal
import sqlite3
import textwrap
import threading

import numpy as np
from mqtt_broker import subscribed_station, wait_until

from appliance.store import Store
from monitor_process import MINUTE, admit, command, start_monitoring

KILLS = 20
OUTAGE = range(5, 11)           # the broker is down through these lives


def notified(data_dir) -> list[tuple]:
    """The events the monitor committed that go to the ward (not its own clock records), as (kind, key, time)."""
    with Store.open(data_dir / "appliance.db") as store:
        return [(e["kind"], e["key"], e["time_s"]) for e in store.events_since(0.0) if e["kind"] != "clock-step"]


def test_no_alarm_is_lost_to_the_ward_across_20_sigkills_and_a_broker_outage(broker, tmp_path, model_cache):
    rng = np.random.default_rng(2027)
    data = tmp_path / "bed"
    (tmp_path / "monitor.toml").write_text(textwrap.dedent(f"""
        [monitor]
        bed_id = "ward3-bed07"
        [notify.mqtt]
        host = "127.0.0.1"
        port = {broker.port}
        """))
    args = [*command(data, model_cache, speed=MINUTE / 0.05), "--config", str(tmp_path / "monitor.toml")]
    admit(data)
    with subscribed_station(broker.port, client_id="ward3-station", keepalive_s=5) as station:
        for life in range(KILLS):
            if life == OUTAGE.start:
                broker.stop()
            if life == OUTAGE.stop:
                broker.start()                          # empty: what it acknowledged before is gone
            process = start_monitoring(args)
            threading.Event().wait(rng.uniform(0.0, 1.0))
            os.kill(process.pid, signal.SIGKILL)
            process.wait()
            process.stdout.close()
        # A last life in real time: its first frame comes at once and the next a minute later, so what it
        # resends and makes is confirmed before it is stopped cleanly.
        process = start_monitoring([*command(data, model_cache, speed=1.0), "--config", str(tmp_path / "monitor.toml")])
        assert wait_until(lambda: not outbox(data, "confirmed_at IS NULL"), 30), \
            f"never confirmed: {outbox(data, 'confirmed_at IS NULL')}"
        process.send_signal(signal.SIGTERM)
        process.communicate(timeout=60)
        open_at_bed = {a["alarm_id"] for a in alarm_state(data)}
        assert wait_until(lambda: set(bed(station)["alarms_by_id"]) == open_at_bed, 10)
    events = notified(data)
    sent = outbox(data)

    assert [(e["kind"], e["key"], e["time_s"]) for _, e, _ in sent] == events     # each once, in order
    assert {by for _, _, by in sent} == {"ward3-station"}
    assert [seq for seq, _, _ in sent] == sorted({seq for seq, _, _ in sent})
    kinds = [kind for kind, _, _ in events]
    assert kinds.count("admitted") == 1 and "raised" in kinds


def outbox(data, where="1") -> list[tuple[int, dict, str | None]]:
    """The bed's outbox as (seq, event, confirmed by), read without writing to it."""
    db = sqlite3.connect(f"file:{data / 'ward-outbox.db'}?mode=ro", uri=True)
    try:
        return [(seq, json.loads(event), by) for seq, event, by in
                db.execute(f"SELECT seq, event, confirmed_by FROM outbox WHERE {where} ORDER BY seq")]
    finally:
        db.close()


def alarm_state(data):
    with Store.open(data / "appliance.db") as store:
        return store.load_state("alerts")["alarms"]["alarms"]


def bed(station):
    bed = next(b for b in station.beds() if b["bed_id"] == "ward3-bed07")
    return {**bed, "alarms_by_id": {a["alarm_id"]: a for a in bed["alarms"]}}
