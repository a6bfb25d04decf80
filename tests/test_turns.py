"""The turn clock on postures and sites: what is a turn, what is not, and reminders that never go quiet."""

import json

import pytest

from appliance.alerts.turns import TurnClock
from appliance.core.pressure_map import HIGH_PRESSURE_KPA
from appliance.errors import ConfigError

MIN = 60.0
LOADED = {"sacrum": 6.0, "heel-left": 7.0, "heel-right": 7.0, "occiput": 5.0}


def run(clock, frames, alarmed=frozenset()):
    """Feed (minute, posture, peaks) frames; the events in order."""
    events = []
    for minute, posture, peaks in frames:
        events += clock.update(minute * MIN, posture, peaks, alarmed)
    return events


def lying(posture, minutes, peaks=LOADED, start=0):
    return [(start + m, posture, peaks) for m in range(minutes)]


def kinds(events):
    return [e.kind for e in events]


def test_lying_down_starts_the_clock_and_is_no_turn():
    clock = TurnClock()
    events = run(clock, [(0, "out-of-bed", {}), (1, "out-of-bed", {})] + lying("supine", 5, start=2))
    assert kinds(events) == ["lay-down"]
    assert events[0].time_s == 2 * MIN and clock.last_turn_s == 2 * MIN


def test_a_change_of_side_is_a_turn_dated_from_when_it_began_and_tilt_wavering_is_not():
    clock = TurnClock()
    frames = lying("supine", 30) + lying("left-30", 10, start=30) + \
        [(40 + m, "left-60" if m % 2 else "left-30", LOADED) for m in range(20)]
    events = run(clock, frames)
    assert kinds(events) == ["lay-down", "repositioned"]
    assert events[1].time_s == 30 * MIN and (events[1].previous, events[1].posture) == ("supine", "left-30")


def test_a_restless_patient_whose_sites_stay_loaded_is_never_turned():
    clock = TurnClock()
    shaky = [(m, "supine", {**LOADED, "sacrum": 5.0 + (m % 3) * 0.4}) for m in range(8 * 60)]
    assert kinds(run(clock, shaky)) == ["lay-down"]
    assert clock.reminder(8 * 60 * MIN) == ("overdue", 1 + (8 * 60 - 120 - 30) // 30)


def test_offloading_most_sites_at_risk_in_the_same_posture_is_a_turn_but_a_brief_lift_is_not():
    clock = TurnClock()
    floated = {"occiput": 5.0}                                # sacrum and both heels relieved
    events = run(clock, lying("supine", 20) + lying("supine", 10, peaks=floated, start=20)   # a skin check
                 + lying("supine", 20, start=30) + lying("supine", 20, peaks=floated, start=50))
    assert kinds(events) == ["lay-down", "repositioned"]
    assert events[1].time_s == 50 * MIN and "heel-left" in events[1].how and "sacrum" in events[1].how


def test_a_site_relieved_for_the_relief_time_has_recovered_and_no_longer_makes_a_small_shift_a_turn():
    """Sites named for a few minutes (a misread posture: ear and trochanter) and long relieved since, then a shift
    that lifts one heel: one of the four sites still at risk is no offloading, though three of six would be half;
    floating the sacrum and the other heel then is."""
    clock = TurnClock()
    misread = {**LOADED, "ear-right": 6.0, "trochanter-right": 6.0}
    one_heel_up = {**LOADED, "heel-left": 1.0}
    events = run(clock, lying("supine", 30) + lying("supine", 8, peaks=misread, start=30)
                 + lying("supine", 60, start=38) + lying("supine", 40, peaks=one_heel_up, start=98))
    assert kinds(events) == ["lay-down"]
    assert clock.at_risk == set(LOADED) - {"heel-left"} and not clock.relieved_since     # the heel recovered too
    floated = run(clock, lying("supine", 20, peaks={"occiput": 5.0, "heel-left": 1.0}, start=138))
    assert kinds(floated) == ["repositioned"] and floated[0].time_s == 138 * MIN


def test_a_posture_misread_for_a_few_minutes_leaves_no_sites_at_risk_that_make_the_return_look_like_a_turn():
    """A supine patient with the arms raised read as lying on the right for 5 min: while misread, the back's own
    sites go unnamed (offloaded, as the clock sees them) and the side's are loaded; back on the back those are
    unloaded. Neither is a turn: the back's sites bore the load throughout but for those minutes."""
    clock = TurnClock()
    back = {"occiput": 10.0, "sacrum": 8.0, "scapula-left": 5.0}
    side = {"ear-right": 20.0, "shoulder-right": 15.0, "trochanter-right": 6.0}
    frames = (lying("supine", 60, peaks=back) + lying("right-90", 5, peaks=side, start=60)
              + lying("supine", 60, peaks=back, start=65))
    assert kinds(run(clock, frames)) == ["lay-down"]
    assert clock.reminder(125 * MIN) == ("due", 0)


def test_a_new_position_counts_only_once_held_for_the_relief_time_and_reminders_wait_meanwhile():
    clock = TurnClock()
    run(clock, lying("supine", 120))
    assert clock.reminder(120 * MIN) == ("due", 0)
    brief = run(clock, lying("right-90", 10, start=120))     # misread, or rolled and back: relieved nothing
    assert clock.turning_since == 120 * MIN and clock.reminder(129 * MIN) is None
    brief += run(clock, lying("supine", 30, start=130))
    assert kinds(brief) == [] and clock.last_turn_s == 0.0 and clock.reminder(159 * MIN) == ("overdue", 1)
    held = run(clock, lying("left-30", 16, start=160))
    assert kinds(held) == ["repositioned"] and held[0].time_s == 160 * MIN and clock.turning_since is None


def test_sitting_up_in_bed_from_a_side_for_longer_than_the_relief_time_is_a_turn_onto_the_back():
    clock = TurnClock()
    events = run(clock, lying("left-30", 60) + lying("inclined", 20, start=60) + lying("supine", 30, start=80))
    assert kinds(events) == ["lay-down", "repositioned"]
    assert events[1].time_s == 60 * MIN and (events[1].previous, events[1].posture) == ("left-30", "inclined")


def test_sitting_up_for_a_meal_is_no_turn_and_the_clock_runs_on():
    clock = TurnClock()
    events = run(clock, lying("supine", 60) + lying("inclined", 30, start=60) + lying("supine", 30, start=90))
    assert kinds(events) == ["lay-down"] and clock.last_turn_s == 0.0


def test_coming_back_to_bed_on_the_other_side_after_a_meal_is_a_turn():
    clock = TurnClock()
    events = run(clock, lying("right-30", 60) + lying("sitting-edge", 20, start=60) + lying("left-30", 20, start=80))
    assert kinds(events) == ["lay-down", "repositioned"] and events[1].time_s == 80 * MIN


def test_a_short_absence_changes_nothing_and_a_long_one_empties_the_bed():
    clock = TurnClock()
    short = run(clock, lying("supine", 30) + [(30 + m, "out-of-bed", {}) for m in range(5)]
                + lying("supine", 5, start=35))
    assert kinds(short) == ["lay-down"] and clock.last_turn_s == 0.0
    long = run(clock, [(40 + m, "out-of-bed", {}) for m in range(30)] + lying("supine", 5, start=70))
    assert kinds(long) == ["bed-empty", "lay-down"]
    assert long[0].time_s == 40 * MIN and long[1].time_s == 70 * MIN and clock.last_turn_s == 70 * MIN


def test_reminders_are_due_then_overdue_and_repeat_until_a_turn():
    clock = TurnClock(interval_s=120 * MIN, grace_s=30 * MIN, repeat_s=30 * MIN)
    run(clock, lying("supine", 2))
    assert clock.reminder(119 * MIN) is None
    assert clock.reminder(120 * MIN) == ("due", 0) and clock.reminder(149 * MIN) == ("due", 0)
    assert clock.reminder(150 * MIN) == ("overdue", 1) and clock.reminder(180 * MIN) == ("overdue", 2)
    clock.record(181 * MIN, "nurse jo", LOADED)
    assert clock.reminder(182 * MIN) is None and clock.due_in_s(181 * MIN) == 120 * MIN


def test_a_turn_recorded_by_hand_names_who_and_reports_an_alarmed_site_still_loaded():
    clock = TurnClock()
    run(clock, lying("supine", 3))
    events = clock.record(10 * MIN, "nurse jo", {"heel-left": 7.0, "sacrum": 1.0},
                          alarmed=frozenset({"heel-left", "sacrum"}))
    assert [(e.kind, e.user, e.site) for e in events] == [("recorded", "nurse jo", None),
                                                           ("still-loaded", None, "heel-left")]
    with pytest.raises(ConfigError, match="needs the name"):
        clock.record(11 * MIN, "  ", {})


def test_a_seen_turn_reports_the_alarmed_sites_it_left_loaded():
    clock = TurnClock()
    events = run(clock, lying("supine", 10) + lying("left-30", 20, peaks={"heel-left": 7.0, "trochanter-left": 9.0},
                                                    start=10), alarmed=frozenset({"heel-left", "sacrum"}))
    assert [(e.kind, e.site) for e in events][1:] == [("repositioned", None), ("still-loaded", "heel-left")]


def test_the_clock_carries_on_after_a_restart():
    frames = lying("supine", 30) + lying("left-30", 5, start=30)          # a turn being held
    whole = TurnClock()
    expected = run(whole, frames + lying("left-30", 15, start=35))
    clock = TurnClock()
    got = run(clock, frames)
    clock = TurnClock().restore(json.loads(json.dumps(clock.state())))
    got += run(clock, lying("left-30", 15, start=35))
    assert kinds(got) == ["lay-down", "repositioned"]
    assert got == expected


@pytest.mark.parametrize("settings", [{"interval_s": 0}, {"repeat_s": -1}, {"grace_s": -5},
                                      {"at_risk_kpa": 0}])
def test_bad_settings_are_refused(settings):
    with pytest.raises(ConfigError, match="turn clock"):
        TurnClock(**settings)


def test_an_unknown_posture_is_refused_by_name():
    with pytest.raises(ConfigError, match="unknown posture 'sideways'"):
        TurnClock().update(0.0, "sideways", {})


def test_the_at_risk_threshold_is_the_alarm_threshold():
    assert TurnClock().at_risk_kpa == HIGH_PRESSURE_KPA
