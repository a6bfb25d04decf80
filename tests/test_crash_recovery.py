"""The real monitor process killed with SIGKILL at random moments and started again on the same data:
site doses, the turn clock and the patient's episode carry on, and no alarm, turn or admission is lost or
repeated, against an uninterrupted night."""

import os
import signal
import subprocess
import time
from collections import Counter

import numpy as np
import pytest

from appliance.store import Store
from monitor_process import MINUTE, admit, command, start_monitoring

NIGHT_S = 43200.0               # supine-unturned: 12 h, one map per simulated minute
KILLS = 20


def night(data_dir):
    """The store's events (kind, key, time) and the alert state it ends with."""
    with Store.open(data_dir / "appliance.db") as store:
        events = [(e["kind"], e["key"], e["time_s"]) for e in store.events_since(0.0)]
        return events, store.load_state("alerts")


def occurrences(events):
    """Each event's time by (kind, key, n), the n-th event of that kind for that key: what a night must hold
    once each, whatever the order of events a minute apart (a killed frame may move a dose crossing by one
    frame, and two heels crossing a minute apart may then cross in the other order)."""
    seen: Counter = Counter()
    out = {}
    for kind, key, time_s in events:
        seen[kind, key] += 1
        out[kind, key, seen[kind, key]] = time_s
    return out


def last_time(data_dir):
    if not (data_dir / "appliance.db").exists():
        return None
    with Store.open(data_dir / "appliance.db") as store:
        state = store.load_state("alerts")
    return None if state is None else state["last_time_s"]


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory, bed_monitoring, model_cache):
    data = tmp_path_factory.mktemp("uninterrupted")
    admit(data)
    subprocess.run(command(data, model_cache, 0), check=True, capture_output=True, timeout=600)
    return night(data)


def test_sigkill_at_20_random_moments_loses_and_repeats_nothing(tmp_path, uninterrupted, model_cache):
    rng = np.random.default_rng(2026)
    data = tmp_path / "killed"
    # 50 ms a frame; each life is killed at a random moment of its first second of monitoring (after its
    # first map line, printed once that frame is committed), whatever the machine's start-up time.
    args = command(data, model_cache, speed=MINUTE / 0.05)
    admit(data)
    progress = []
    for _ in range(KILLS):
        process = start_monitoring(args)
        time.sleep(rng.uniform(0.0, 1.0))
        os.kill(process.pid, signal.SIGKILL)
        process.wait()
        process.stdout.close()
        assert process.returncode == -signal.SIGKILL
        progress.append(last_time(data))
    subprocess.run(command(data, model_cache, 0), check=True, capture_output=True, timeout=600)
    events, state = night(data)
    expected, expected_state = uninterrupted

    assert all(0 <= t < NIGHT_S for t in progress) and progress == sorted(set(progress)), \
        f"every kill must land mid-night, each life having monitored; store times {progress}"
    got, want = occurrences(events), occurrences(expected)
    assert got.keys() == want.keys(), \
        f"lost {sorted(want.keys() - got.keys())}, repeated or added {sorted(got.keys() - want.keys())}"
    assert all(abs(got[k] - want[k]) <= MINUTE for k in want), \
        [(k, got[k], want[k]) for k in want if abs(got[k] - want[k]) > MINUTE]
    assert state["last_time_s"] == expected_state["last_time_s"] == NIGHT_S
    assert state["dose"]["sites"] == expected_state["dose"]["sites"]
    dose, dose0 = (np.array(s["dose"]["cells"]["dose"], dtype=float) for s in (state, expected_state))
    one_frame = dose0 * MINUTE / NIGHT_S                      # what a minute adds under constant pressure
    assert dose0.max() > 1.0 and np.all(np.abs(dose - dose0) <= one_frame + 1e-9)
    turns, turns0 = state["turns"], expected_state["turns"]
    assert abs(turns["last_turn_s"] - turns0["last_turn_s"]) <= MINUTE
    assert (turns["posture"], turns["reference"]) == (turns0["posture"], turns0["reference"])
    assert state["episode"] == expected_state["episode"] and state["episode"]["patient_id"] == "MRN-0042"
    assert [kind for kind, _, _ in events].count("admitted") == 1
