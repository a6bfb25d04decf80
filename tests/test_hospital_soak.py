"""The hospital soak, short (``benchmarks/hospital.py``; its report has the long run): beds on their own ward
links and outboxes, a real three-node engine and the product's ward stations as processes, alarm changes under
every kind of fault in turn (the ward stream's leader SIGKILLed, one ward's beds cut off, two of the three nodes
SIGSTOPped, a station process SIGKILLed), and the beds' and stations' own records read afterwards."""

import pytest
from hospital import COMPRESSED, Plan, measure, soak

pytestmark = pytest.mark.filterwarnings(
    # nats-py leaves the stream writer of a reconnection whose handshake failed for the collector, which warns
    "ignore:Exception ignored in. <function StreamWriter.__del__:pytest.PytestUnraisableExceptionWarning")

CONFIRM_TIMEOUT_S = 3.0
"""Short enough that the cut ward's beds raise their technical alarm well inside the cut, however busy the
machine."""


def test_no_alarm_is_lost_or_shown_twice_under_every_fault_and_the_cut_ward_raises_its_technical_alarm(tmp_path):
    plan = Plan(beds=24, ward_size=6, duration_s=180.0, transport="engine", rate=20.0, timing=COMPRESSED,
                confirm_timeout_s=CONFIRM_TIMEOUT_S)
    run, faults = soak(plan, tmp_path, progress=lambda _: None)
    assert {fault.kind for fault in faults} == {"kill", "cut", "pause", "station"}
    assert [entry["step"] for entry in run.faults].count("heal") == len(faults)
    m = measure(tmp_path, plan, run)
    assert m.events > 1000
    assert m.confirmed == m.events and m.unconfirmed_at_end == 0
    assert m.lost == 0 and m.confirmed_lost == 0
    assert m.shown_twice_lives == 0 and m.shown_twice_content == 0
    assert m.drain_after_faults_s is not None and m.empty_after_load_s is not None    # every outbox emptied
    [cut] = m.technical
    assert cut["raised"] == cut["beds"] == plan.ward_size            # every bed of the cut ward raised it
    assert cut["cleared"] == cut["beds"]                              # and cleared it once the link was mended


@pytest.mark.background
def test_300_beds_for_30_minutes_lose_no_alarm_and_show_none_twice_under_every_fault(background_soak):
    """The soak ward IT asks for, at its full size (benchmarks/hospital.md has its latencies): 300 beds at 50 alarm
    changes a second for 30 minutes, the ward stream's leader killed every 2 minutes, a ward cut off, two of the
    three servers stopped, a station crashed. Run beside the rest of the suite, so on a busy machine."""
    m = background_soak.result()
    assert m["beds"] == 300 and m["events"] > 80_000, background_soak.report()
    kinds = [f["kind"] for f in m["faults"] if f["step"] == "start"]
    assert kinds.count("kill") >= 10 and {"cut", "pause", "station"} <= set(kinds)
    assert m["confirmed"] == m["events"] and m["unconfirmed_at_end"] == 0
    assert m["lost"] == 0 and m["confirmed_lost"] == 0, m["lost_examples"]
    assert m["shown_twice_lives"] == 0 and m["shown_twice_content"] == 0
    assert m["drain_after_faults_s"] is not None
    assert m["empty_after_load_s"] is not None and m["empty_after_load_s"] <= 60.0    # the requirement, not a timing
    assert m["technical"] and all(cut["raised"] == cut["cleared"] == cut["beds"] for cut in m["technical"])
