"""The ward station under a ward's load, end to end: 50 beds at 1 frame/s through a real Mosquitto to the
station's web view (``appliance ward``), read as a nurse reads it, over the server-sent event stream.

A shorter run of ``benchmarks/ward_load.py`` (its report has the long one): the 50 production publishers in a
load-generator process, three probe beds in their own processes stopped during the run (frozen, killed,
closed), and the benchmark's client logged in over HTTP. About a minute.
"""

import statistics

import pytest
import ward_load  # benchmarks/, on the path by conftest

from appliance.ward.station import STALE_MARGIN_S

pytestmark = pytest.mark.slow

DURATION_S = 35.0
STREAM_POLL_S = 0.25          # the ward view checks the station for changes four times a second


@pytest.fixture(scope="module")
def result():
    """One run, shared by the tests below; every process it starts is ended before it returns."""
    out = ward_load.run(beds=50, duration_s=DURATION_S, probes_per_kind=1, seed=7, use_stand_in=False,
                        say=lambda line: print(f"ward load: {line}"))
    latencies = list(out["latencies_s"].values())
    print(f"ward load: {out['alarms_raised']} alarms, latency median {statistics.median(latencies):.3f} s, "
          f"p95 {ward_load.percentile(latencies, 0.95):.3f} s, max {max(latencies):.3f} s; offline "
          f"{ {bed: round(v['offline_s'] or -1, 2) for bed, v in out['offline'].items()} }; CPU "
          f"{ {k: round(100 * v, 1) for k, v in out['cpu'].items()} } %; broker {out['broker_per_s']}")
    return out


def test_the_run_was_the_load_asked_for(result):
    generated = result["generator"]
    assert result["station"] == "appliance ward"
    assert generated["frames"] == 50 * DURATION_S                      # 50 beds, 1 frame/s each
    assert generated["late_frames"] <= generated["frames"] // 100 and generated["summaries_skipped"] == 0
    assert generated["summaries_sent"] == generated["frames"]          # every frame's summary went out
    assert generated["events_unconfirmed"] == 0                        # every event confirmed by the station
    assert result["stream"]["most_beds_shown"] == 53                   # the 50 and the three probes
    assert result["load_beds_shown_offline"] == []                     # none of the 50 missed while running
    assert result["alarms_raised"] >= 50 and result["acks"] >= 15      # each bed some 1.5 alarms in the run
    assert result["broker_per_s"]["publish/in (beds' own counts)"] > 50


def test_a_new_alarm_is_on_the_ward_view_within_2_s_and_none_is_lost(result):
    latencies = list(result["latencies_s"].values())
    assert result["alarms_lost"] == [] and len(latencies) == result["alarms_raised"]
    assert ward_load.percentile(latencies, 0.95) < 2.0
    assert max(latencies) < 5.0 and min(latencies) > 0
    assert ward_load.percentile(result["generator"]["confirm_latencies_s"], 0.95) < 2.0    # and back at the bed


def test_the_view_never_shows_an_alarm_twice_an_ended_one_or_one_never_raised(result):
    assert result["duplicates_shown"] == 0 and result["bed_repeats"] == 0
    assert result["stuck_alarms"] == [] and result["unexpected_alarms"] == []
    assert ward_load.percentile(result["ack_latencies_s"], 0.95) < 2.0   # and it shows who acknowledged


def test_a_stopped_bed_shows_offline_within_the_keepalive(result):
    keepalive_s = result["bed_keepalive_s"]
    offline = {v["kind"]: v for v in result["offline"].values()}
    # Killed (the kernel closes its socket: the broker gives the last will) or closed cleanly: at once.
    assert offline["killed"]["offline_s"] < 1.0 and offline["killed"]["status_offline_s"] < 1.0
    assert offline["closed"]["offline_s"] < 1.0 and offline["closed"]["status_offline_s"] < 1.0
    # Frozen with its connection open: offline by silence, 4 s (3 summary intervals + STALE_MARGIN_S) after its
    # last message, seen within one poll of the stream: within the keep-alive even at the least a bed may set.
    frozen = offline["frozen"]
    assert frozen["offline_s"] <= keepalive_s
    assert frozen["offline_after_last_message_s"] <= 3 * 1.0 + STALE_MARGIN_S + STREAM_POLL_S + 0.35
    # and the broker's last will comes too (Mosquitto 2.0.11 gives it up to 2.6 keep-alives late)
    assert frozen["status_offline_s"] is not None and frozen["status_offline_s"] <= 3 * keepalive_s + 1


def test_the_broker_and_station_keep_up_with_a_ward_easily(result):
    assert result["cpu"]["broker"] < 0.10          # shares of one core; measured about 0.005
    assert result["cpu"]["station"] < 0.30         # measured about 0.03
