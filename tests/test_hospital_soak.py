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
