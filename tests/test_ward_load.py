"""The ward station under a ward's load, end to end: 50 beds at 1 frame/s through a real Mosquitto to the
station's web view (``appliance ward``), read as a nurse reads it, over the server-sent event stream.

A shorter run of ``benchmarks/ward_load.py`` (its report has the long one): the 50 production publishers in a
load-generator process, three probe beds in their own processes stopped during the run (frozen, killed,
closed), and the benchmark's client logged in over HTTP. About a minute. What the run shows is asserted here;
how fast (latencies, CPU) is the benchmark's to report, since a busy machine slows it.
"""

import statistics

import pytest
import ward_load  # benchmarks/, on the path by conftest

from appliance.ward.board import STALE_MARGIN_S

pytestmark = pytest.mark.slow

DURATION_S = 35.0


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
    assert generated["summaries_skipped"] == 0     # how late frames came is the benchmark's to report: timing
    assert generated["summaries_sent"] == generated["frames"]          # every frame's summary went out
    assert generated["events_unconfirmed"] == 0                        # every event confirmed by the station
    assert result["stream"]["most_beds_shown"] == 53                   # the 50 and the three probes
    assert result["load_beds_shown_offline"] == []                     # none of the 50 missed while running
    assert result["alarms_raised"] >= 50 and result["acks"] >= 15      # each bed some 1.5 alarms in the run
    assert result["broker_per_s"]["publish/in (beds' own counts)"] > 50


def test_every_new_alarm_reaches_the_ward_view_and_comes_back_confirmed(result):
    latencies = list(result["latencies_s"].values())
    assert result["alarms_lost"] == [] and len(latencies) == result["alarms_raised"]
    assert min(latencies) > 0                                       # shown after it was raised, never before
    assert len(result["generator"]["confirm_latencies_s"]) >= result["alarms_raised"]   # and back at the bed


def test_the_view_never_shows_an_alarm_twice_an_ended_one_or_one_never_raised(result):
    assert result["duplicates_shown"] == 0 and result["bed_repeats"] == 0
    assert result["stuck_alarms"] == [] and result["unexpected_alarms"] == []
    assert result["ack_latencies_s"] and min(result["ack_latencies_s"]) > 0   # and who acknowledged, once done


def test_a_stopped_bed_shows_offline_however_it_stopped(result):
    offline = {v["kind"]: v for v in result["offline"].values()}
    # Killed (the kernel closes its socket: the broker gives the last will) or closed cleanly.
    for kind in ("killed", "closed"):
        assert offline[kind]["offline_s"] is not None and offline[kind]["status_offline_s"] is not None, kind
    # Frozen with its connection open: offline by silence, and not before 3 summary intervals and the margin.
    frozen = offline["frozen"]
    assert frozen["offline_s"] is not None
    assert frozen["offline_after_last_message_s"] >= 3 * 1.0 + STALE_MARGIN_S - 0.1   # heard to 0.1 s
    assert frozen["status_offline_s"] is not None                   # and the broker's last will comes too
