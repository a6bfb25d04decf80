"""Alarm engine: behaviour and times of raise, end, latching, acknowledgement, audio pause, escalation, restart."""

import json

import pytest

from appliance.alerts.alarms import AlarmCondition, AlarmEngine, Escalation
from appliance.errors import ConfigError

TURN_DUE = AlarmCondition("pressure:sacrum:7", "clinical", "low", False, "Reposition due",
                          escalation=(Escalation(600.0, "ward-station"),))
ELECTRODE = AlarmCondition("technical:electrode:5", "technical", "medium", True, "Electrode 5 fault")
HEEL = AlarmCondition("pressure:heel-left:7", "clinical", "low", False, "Reposition due")
LADDER = AlarmCondition("pressure:sacrum:8", "clinical", "low", False, "Reposition due",
                        escalation=(Escalation(300.0, "charge-nurse"), Escalation(600.0, "ward-station")))


def on(*conditions, detail=None):
    return {c.key: (c, detail) for c in conditions}


def kinds(events):
    return [e.kind for e in events]


def test_non_latching_alarm_raises_stays_and_ends_by_itself():
    engine = AlarmEngine()
    raised = engine.assess(0.0, on(TURN_DUE, detail="D = 1.02"))
    assert kinds(raised) == ["raised"]
    assert raised[0].priority == "low" and raised[0].message == "Reposition due: D = 1.02"
    assert engine.assess(10.0, on(TURN_DUE)) == []
    assert [a.key for a in engine.clinical()] == [TURN_DUE.key]
    ended = engine.assess(20.0, {})
    assert kinds(ended) == ["ended"] and ended[0].time_s == 20.0
    assert engine.alarms() == [] and engine.audible(20.0) is None


def test_latching_alarm_waits_for_acknowledgement_after_condition_clears():
    engine = AlarmEngine()
    [raised] = engine.assess(0.0, on(ELECTRODE))
    assert kinds(engine.assess(5.0, {})) == ["cleared-awaiting-ack"]
    assert engine.alarm(raised.alarm_id).state == "cleared-awaiting-ack"
    assert engine.audible(6.0) == "medium", "a latched alarm keeps signalling"
    assert engine.assess(30.0, {}) == []
    events = engine.acknowledge(40.0, raised.alarm_id, "nurse.kim")
    assert kinds(events) == ["acknowledged", "ended"]
    assert all(e.user == "nurse.kim" and e.time_s == 40.0 for e in events)
    assert engine.alarms() == []


def test_latched_alarm_whose_condition_returns_is_the_same_alarm():
    engine = AlarmEngine()
    [raised] = engine.assess(0.0, on(ELECTRODE))
    engine.assess(5.0, {})
    again = engine.assess(8.0, on(ELECTRODE))
    assert kinds(again) == ["reactivated"] and again[0].alarm_id == raised.alarm_id


def test_acknowledgement_needs_a_named_user_and_is_recorded():
    engine = AlarmEngine()
    [raised] = engine.assess(0.0, on(TURN_DUE))
    for nobody in ("", "   ", None):
        with pytest.raises(ConfigError, match="named user"):
            engine.acknowledge(1.0, raised.alarm_id, nobody)
    [ack] = engine.acknowledge(2.0, raised.alarm_id, "nurse.kim")
    assert (ack.kind, ack.user, ack.time_s, ack.alarm_id) == ("acknowledged", "nurse.kim", 2.0, raised.alarm_id)
    assert engine.acknowledge(3.0, raised.alarm_id, "nurse.lee") == [], "a second press changes nothing"
    # Acknowledged active non-latching alarm: visible, silent, ends when its condition clears.
    assert [a.alarm_id for a in engine.alarms()] == [raised.alarm_id]
    assert engine.audible(4.0) is None
    assert kinds(engine.assess(5.0, {})) == ["ended"]
    with pytest.raises(ConfigError, match="already ended"):
        engine.acknowledge(6.0, raised.alarm_id, "nurse.kim")


def test_acknowledgement_does_not_silence_new_conditions():
    engine = AlarmEngine()
    [first] = engine.assess(0.0, on(TURN_DUE))
    engine.acknowledge(1.0, first.alarm_id, "nurse.kim")
    engine.assess(2.0, on(TURN_DUE, HEEL))
    assert engine.audible(2.0) == "low"


def test_audio_pause_times_out_at_the_stated_time():
    engine = AlarmEngine(max_audio_pause_s=120.0)
    engine.assess(0.0, on(TURN_DUE))
    [paused] = engine.pause_audio(10.0, "nurse.kim", 60.0)
    assert (paused.kind, paused.user, paused.alarm_id) == ("audio-paused", "nurse.kim", None)
    assert engine.audible(10.0) is None and engine.audible(69.9) is None
    assert engine.audible(70.0) == "low"
    resumed = engine.assess(75.0, on(TURN_DUE))
    assert kinds(resumed) == ["audio-resumed"] and resumed[0].time_s == 70.0


def test_audio_pause_refuses_over_long_or_anonymous_pauses():
    engine = AlarmEngine(max_audio_pause_s=120.0)
    with pytest.raises(ConfigError, match="at most 120 s"):
        engine.pause_audio(0.0, "nurse.kim", 121.0)
    with pytest.raises(ConfigError):
        engine.pause_audio(0.0, "nurse.kim", 0.0)
    with pytest.raises(ConfigError, match="named user"):
        engine.pause_audio(0.0, "", 30.0)
    assert engine.history == []


def test_audio_pause_of_one_alarm_leaves_the_others_loud():
    engine = AlarmEngine()
    [_, electrode] = engine.assess(0.0, on(TURN_DUE, ELECTRODE))
    engine.pause_audio(1.0, "nurse.kim", 100.0, alarm_id=electrode.alarm_id)
    assert engine.audible(2.0) == "low"
    assert engine.audible(101.0) == "medium"
    [resumed] = engine.tick(150.0)
    assert (resumed.kind, resumed.alarm_id, resumed.time_s) == ("audio-resumed", electrode.alarm_id, 101.0)


def test_escalation_fires_once_at_the_stated_time_with_channel_and_raised_priority():
    engine = AlarmEngine()
    [raised] = engine.assess(100.0, on(TURN_DUE))
    assert all(engine.assess(float(t), on(TURN_DUE)) == [] for t in range(101, 700))  # one frame a second
    [escalated] = engine.assess(700.0, on(TURN_DUE))
    assert (escalated.kind, escalated.time_s, escalated.priority, escalated.channel) == (
        "escalated", 700.0, "medium", "ward-station")
    assert escalated.alarm_id == raised.alarm_id
    assert all(e.kind != "escalated" for t in range(701, 2000) for e in engine.assess(float(t), on(TURN_DUE)))
    assert engine.alarm(raised.alarm_id).priority == "medium" and engine.audible(2000.0) == "medium"


def test_escalation_between_frames_is_stamped_with_its_due_time():
    engine = AlarmEngine()
    engine.assess(0.0, on(LADDER))
    events = engine.assess(1000.0, {})
    assert [(e.kind, e.time_s, e.priority, e.channel) for e in events] == [
        ("escalated", 300.0, "medium", "charge-nurse"),
        ("escalated", 600.0, "high", "ward-station"),
        ("ended", 1000.0, "high", None)]


def test_no_escalation_after_acknowledgement():
    engine = AlarmEngine()
    [raised] = engine.assess(0.0, on(TURN_DUE))
    engine.acknowledge(599.0, raised.alarm_id, "nurse.kim")
    assert engine.assess(5000.0, on(TURN_DUE)) == []
    assert engine.alarm(raised.alarm_id).priority == "low"


def test_technical_and_clinical_alarms_are_kept_apart():
    engine = AlarmEngine()
    engine.assess(0.0, on(ELECTRODE, TURN_DUE))
    assert [a.key for a in engine.technical()] == [ELECTRODE.key]
    assert [a.key for a in engine.clinical()] == [TURN_DUE.key]
    [electrode] = engine.technical()
    engine.acknowledge(1.0, electrode.alarm_id, "tech.ana")
    assert engine.audible(1.0) == "low", "acknowledging the technical alarm leaves the clinical one sounding"
    assert [a.key for a in engine.clinical()] == [TURN_DUE.key]


def test_ids_are_unique_increasing_and_new_on_reraise():
    engine = AlarmEngine()
    ids = [e.alarm_id for e in engine.assess(0.0, on(TURN_DUE, HEEL))]
    engine.assess(1.0, {})
    ids += [e.alarm_id for e in engine.assess(2.0, on(TURN_DUE))]
    assert ids == sorted(set(ids)) and len(ids) == 3


def test_state_round_trip_mid_alarm_keeps_alarms_and_escalation_times():
    engine = AlarmEngine(max_audio_pause_s=90.0)
    [raised, _] = engine.assess(0.0, on(TURN_DUE, ELECTRODE))
    engine.assess(200.0, on(TURN_DUE))  # electrode clears, latched
    restored = AlarmEngine.from_state(json.loads(json.dumps(engine.state())))

    events = restored.assess(300.0, on(TURN_DUE))
    assert events == [], "no duplicate raise for alarms already active before the restart"
    assert [a.state for a in restored.alarms()] == ["cleared-awaiting-ack", "active"]
    assert restored.max_audio_pause_s == 90.0
    assert restored.assess(599.0, on(TURN_DUE)) == []
    [escalated] = restored.assess(600.0, on(TURN_DUE))
    assert (escalated.kind, escalated.alarm_id, escalated.time_s) == ("escalated", raised.alarm_id, 600.0)
    [new] = restored.assess(601.0, on(TURN_DUE, HEEL))
    assert new.alarm_id == 3, "ids continue after the restart"


def test_malformed_state_and_backwards_time_are_refused():
    with pytest.raises(ConfigError):
        AlarmEngine.from_state({"version": 99})
    with pytest.raises(ConfigError, match="malformed"):
        AlarmEngine.from_state({"version": 1})
    engine = AlarmEngine()
    engine.assess(10.0, {})
    with pytest.raises(ConfigError, match="backwards"):
        engine.assess(9.0, {})


def test_bad_conditions_are_refused():
    with pytest.raises(ConfigError):
        AlarmCondition("x", "physio", "low", False, "m")
    with pytest.raises(ConfigError):
        AlarmCondition("x", "clinical", "urgent", False, "m")
    with pytest.raises(ConfigError, match="increasing"):
        AlarmCondition("x", "clinical", "low", False, "m",
                       escalation=(Escalation(600.0, "a"), Escalation(300.0, "b")))
    with pytest.raises(ConfigError, match="with that key"):
        AlarmEngine().assess(0.0, {"other": (TURN_DUE, None)})


def test_history_is_complete_and_ordered():
    engine = AlarmEngine()
    returned = []
    returned += engine.assess(0.0, on(TURN_DUE, ELECTRODE))
    returned += engine.pause_audio(10.0, "nurse.kim", 60.0)
    returned += engine.assess(650.0, on(TURN_DUE))
    returned += engine.acknowledge(660.0, engine.technical()[0].alarm_id, "tech.ana")
    returned += engine.assess(700.0, {})
    assert engine.history == returned
    assert kinds(engine.history) == ["raised", "raised", "audio-paused", "audio-resumed", "escalated",
                                     "cleared-awaiting-ack", "acknowledged", "ended", "ended"]
    times = [e.time_s for e in engine.history]
    assert times == sorted(times)
