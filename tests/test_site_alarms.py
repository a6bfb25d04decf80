"""Alarms per tissue site, reminders and episodes, on a scripted body: the posture and the located sites are
given frame by frame, so the alert logic is checked apart from the posture model and the site locator."""

import json
from dataclasses import dataclass

import numpy as np
import pytest

from appliance.alerts.episodes import Episode
from appliance.alerts.pipeline import AlertPipeline, AlertSettings
from appliance.alerts.posture import PostureEstimate
from appliance.core.named_layouts import get_layout
from appliance.core.pixels import pixel_grid
from appliance.core.pressure import KPA_PER_MMHG
from appliance.core.pressure_map import PressureMap
from appliance.errors import ConfigError

GRID = pixel_grid(get_layout("grid-16x32"))
MIN = 60.0
SACRUM_MMHG = 60.0          # tolerable for 6.3 h on the Reswick-Rogers curve


@dataclass(frozen=True)
class Reading:
    site: str | None
    along_mm: float
    across_mm: float
    peak_kpa: float


class ScriptedBody:
    """The posture and site readings the pipeline is told it sees, changed between frames."""

    def __init__(self):
        self.posture, self.readings = "out-of-bed", []

    def classify(self, view):
        return PostureEstimate.certain(self.posture)

    def locate(self, view, posture):
        return list(self.readings)

    def lie(self, posture, **sites_mmhg_at):
        self.posture = posture
        self.readings = [Reading(site, along, across, mmhg * KPA_PER_MMHG)
                         for site, (mmhg, along, across) in sites_mmhg_at.items()]


def pipeline_for(body, settings=AlertSettings()):
    return AlertPipeline(GRID, settings, classify=body.classify, locate=body.locate)


def frame(minute, loaded=True):
    kpa = np.zeros(GRID.shape)
    if loaded:
        kpa[14:16, 28:31] = 50 * KPA_PER_MMHG
    return PressureMap(minute * MIN, kpa, [], None, 0)


def raised(events, prefix="pressure:"):
    return [e for e in events if e.kind == "raised" and e.key.startswith(prefix)]


def run(pipeline, body, minutes, start=0, **scene):
    events = []
    for m in range(start, start + minutes):
        if scene:
            scene_now = {k: (v(m) if callable(v) else v) for k, v in scene.items()}
            body.lie(scene_now.pop("posture", body.posture), **scene_now)
        out = pipeline.update(frame(m, body.posture != "out-of-bed"))
        events += [pipeline.record(e) for e in out.turn_events + out.alarm_events]
    return events


def test_a_site_keeps_its_dose_as_the_patient_slides_and_alarms_once_where_it_lies():
    body = ScriptedBody()
    pipeline = pipeline_for(body)
    events = run(pipeline, body, 8 * 60, posture="supine",
                 sacrum=lambda m: (SACRUM_MMHG, 850.0 + m, 450.0))            # slides 1 mm a minute
    sacral = raised(events)
    assert [e.site for e in sacral] == ["sacrum"]
    tolerable_min = pipeline.curve.tolerable_s(SACRUM_MMHG * KPA_PER_MMHG) / 60
    assert sacral[0].time_s / 60 == pytest.approx(tolerable_min, abs=1.0)
    assert (sacral[0].x_mm, sacral[0].y_mm) == pytest.approx((850.0 + sacral[0].time_s / 60, 450.0))
    assert sacral[0].posture == "supine"


def test_two_sites_whose_loads_merge_keep_their_own_doses():
    body = ScriptedBody()
    pipeline = pipeline_for(body)
    run(pipeline, body, 60, posture="supine", sacrum=(SACRUM_MMHG, 850.0, 450.0),
        **{"ischium-left": (40.0, 900.0, 500.0)})
    doses = pipeline.dose.doses()
    for site, mmhg in (("sacrum", SACRUM_MMHG), ("ischium-left", 40.0)):      # each its own pressure's dose
        assert doses[site] == pytest.approx(59 * MIN / pipeline.curve.tolerable_s(mmhg * KPA_PER_MMHG), rel=1e-9)
    assert doses["sacrum"] > doses["ischium-left"]


def test_a_site_the_locator_stops_naming_is_dosed_where_it_lay_until_that_place_is_relieved():
    body = ScriptedBody()
    pipeline = pipeline_for(body)
    events = run(pipeline, body, 7 * 60, posture="supine", sacrum=(SACRUM_MMHG, 850.0, 450.0))
    assert raised(events)
    before = pipeline.dose.doses()["sacrum"]
    body.readings = []                                  # the name comes and goes; the tissue is still loaded
    unnamed = run(pipeline, body, 10, start=7 * 60)
    assert not [e for e in unnamed if e.kind == "ended" and e.key == "pressure:sacrum"]
    where_it_lay = 50 * KPA_PER_MMHG                    # the frames' load lies within reach of its place
    assert pipeline.dose.doses()["sacrum"] == pytest.approx(
        before + 10 * MIN / pipeline.curve.tolerable_s(where_it_lay), rel=1e-9)
    relieved = []
    for m in range(7 * 60 + 10, 7 * 60 + 26):          # the place unloaded for the relief time: the alarm ends
        relieved += pipeline.update(frame(m, loaded=False)).alarm_events
    assert [e.key for e in relieved if e.kind == "ended" and e.key.startswith("pressure:")] == ["pressure:sacrum"]


def test_a_site_last_seen_unloaded_is_not_dosed_with_a_neighbours_load_when_the_locator_loses_it():
    body = ScriptedBody()
    pipeline = pipeline_for(body)
    run(pipeline, body, 60, posture="supine", sacrum=(SACRUM_MMHG, 850.0, 450.0))
    assert pipeline.dose.doses()["sacrum"] > 0.1
    run(pipeline, body, 3, start=60, posture="supine", sacrum=(25.0, 850.0, 450.0))    # offloaded, still named
    body.readings = []                                  # then lost; the frames' 50 mmHg lies within reach of it
    run(pipeline, body, 15, start=63)
    assert pipeline.dose.doses()["sacrum"] == 0.0       # relieved for 18 min: the neighbour's load is not its own
    body.lie("supine", sacrum=(SACRUM_MMHG, 850.0, 450.0))
    run(pipeline, body, 1, start=78)
    body.readings = []                                  # lost while loaded: followed again
    run(pipeline, body, 5, start=79)
    assert pipeline.dose.doses()["sacrum"] == pytest.approx(
        MIN / pipeline.curve.tolerable_s(SACRUM_MMHG * KPA_PER_MMHG)
        + 5 * MIN / pipeline.curve.tolerable_s(50 * KPA_PER_MMHG), rel=1e-9)


def test_a_turn_to_another_posture_group_stops_following_where_the_sites_lay():
    body = ScriptedBody()
    pipeline = pipeline_for(body)
    run(pipeline, body, 60, posture="supine", sacrum=(SACRUM_MMHG, 850.0, 450.0))
    body.lie("left-30")                                 # no site named; the frames' load stays where it was
    run(pipeline, body, 20, start=60)
    assert pipeline.posture == "left-30" and pipeline.dose.doses()["sacrum"] == 0.0


def test_a_restless_night_raises_one_sacral_alarm_per_dose_crossing():
    body = ScriptedBody()
    pipeline = pipeline_for(body)
    jitter = np.random.default_rng(3)
    shifts = jitter.uniform(-40, 40, size=(16 * 60, 2))
    events = run(pipeline, body, 16 * 60, posture="supine",
                 sacrum=lambda m: (SACRUM_MMHG * (0.85 if m % 7 == 0 else 1.0), 850 + shifts[m][0],
                                   450 + shifts[m][1]))
    assert len(raised(events)) == 1
    assert not [e for e in events if e.type == "turn" and e.kind == "repositioned"]


def test_reminders_are_medium_when_due_high_when_overdue_and_repeated_until_a_turn():
    body = ScriptedBody()
    pipeline = pipeline_for(body)
    events = run(pipeline, body, 4 * 60, posture="supine", sacrum=(30.0, 850.0, 450.0))
    turn = [(e.time_s / 60, e.key, e.priority) for e in raised(events, "turn:")]
    assert turn == [(120, "turn:due", "medium"), (150, "turn:overdue:1", "high"), (180, "turn:overdue:2", "high"),
                    (210, "turn:overdue:3", "high")]
    assert [e.channel for e in events if e.kind == "escalated" and e.key == "turn:overdue:1"] == ["ward-station"]
    recorded = pipeline.record_turn(4 * 60 * MIN, "nurse jo")
    assert [e.kind for e in recorded] == ["recorded"]
    after = run(pipeline, body, 5, start=4 * 60)
    assert [e.key for e in after if e.kind == "ended"] == ["turn:overdue:3"]


def test_a_turned_patient_gets_no_pressure_alarm_and_no_overdue_reminder():
    body = ScriptedBody()
    pipeline = pipeline_for(body)
    cycle = ["supine", "left-30", "supine", "right-30"]
    sites = {"supine": {"sacrum": (SACRUM_MMHG, 850.0, 450.0)},
             "left-30": {"trochanter-left": (70.0, 930.0, 600.0)},
             "right-30": {"trochanter-right": (70.0, 930.0, 300.0)}}
    events = []
    for m in range(24 * 60):
        posture = cycle[(m // 120) % 4]
        body.lie(posture, **sites[posture])
        out = pipeline.update(frame(m))
        events += [pipeline.record(e) for e in out.turn_events + out.alarm_events]
    assert not raised(events) and not raised(events, "turn:overdue")
    assert len([e for e in events if e.kind == "repositioned"]) == 11


class UnsureBody(ScriptedBody):
    """A body the posture model reads, for a while, as lying on the right side with little certainty (as it
    reads a supine patient with the arms raised); the locator names what it is told the posture is."""

    unsure = False

    def classify(self, view):
        if not self.unsure:
            return super().classify(view)
        return PostureEstimate("right-90", 0.56, {"right-90": 0.56, "inclined": 0.24, "supine": 0.20})

    def locate(self, view, posture):
        site = "trochanter-right" if posture == "right-90" else "sacrum"
        return [Reading(site, 850.0, 450.0, SACRUM_MMHG * KPA_PER_MMHG)]


def test_an_unsure_posture_is_no_turn_and_renames_no_site():
    body = UnsureBody()
    pipeline = pipeline_for(body)
    events = run(pipeline, body, 60, posture="supine")
    body.unsure = True
    events += run(pipeline, body, 6 * 60, start=60)
    assert (pipeline.posture, pipeline.posture_sure) == ("supine", False)
    assert not [e for e in events if e.kind == "repositioned"]
    assert [e.site for e in raised(events)] == ["sacrum"]                     # one dose, never split
    assert "turn:due" in [e.key for e in raised(events, "turn:")]
    body.unsure = False
    body.posture = "right-90"                                                  # sure now: a turn
    later = run(pipeline, body, 17, start=7 * 60)
    assert [e.posture for e in later if e.kind == "repositioned"] == ["right-90"]
    assert pipeline.posture_sure


def test_admitting_a_new_patient_starts_doses_and_clock_afresh_and_keeps_the_old_ones_history():
    body = ScriptedBody()
    pipeline = pipeline_for(body)
    run(pipeline, body, 2, posture="out-of-bed")
    admitted = pipeline.admit(2 * MIN, Episode("MRN-1", 2 * MIN, "nurse jo", name="A. Patient", braden=14))
    assert [(e.type, e.kind, e.patient) for e in admitted] == [("episode", "admitted", "MRN-1")]
    first = run(pipeline, body, 8 * 60, start=3, posture="supine", sacrum=(SACRUM_MMHG, 850.0, 450.0))
    assert raised(first) and all(e.patient == "MRN-1" for e in first)
    handover = pipeline.admit(8 * 60 * MIN + 3 * MIN, Episode("MRN-2", 8 * 60 * MIN + 3 * MIN, "nurse kim"))
    assert [(e.kind, e.patient) for e in handover][-2:] == [("discharged", "MRN-1"), ("admitted", "MRN-2")]
    assert ("ended", "pressure:sacrum", "MRN-1") in [(e.kind, e.key, e.patient) for e in handover]
    assert max(pipeline.dose.doses().values()) == 0.0 and pipeline.turns.last_turn_s is None
    second = run(pipeline, body, 10, start=8 * 60 + 3)
    assert [e.kind for e in second if e.type == "turn"] == ["lay-down"] and not raised(second)
    assert all(e.patient == "MRN-2" for e in second)


def test_discharge_without_a_patient_is_refused():
    with pytest.raises(ConfigError, match="no patient is admitted"):
        pipeline_for(ScriptedBody()).discharge(0.0, "nurse jo")


@pytest.mark.parametrize("fields, message", [({"patient_id": ""}, "patient identifier"),
                                             ({"braden": 30}, "Braden score"), ({"braden": 12.5}, "Braden score"),
                                             ({"bed_exit_after_s": 1.0}, "bed-exit delay"),
                                             ({"name": "x" * 101}, "at most 100")])
def test_a_bad_episode_is_refused_naming_the_field(fields, message):
    with pytest.raises(ConfigError, match=message):
        Episode(**{"patient_id": "MRN-1", "admitted_s": 0.0, "admitted_by": "nurse jo", **fields})


@pytest.mark.parametrize("alert, expected", [(False, []), (True, ["bed-exit"])])
def test_leaving_the_bed_alerts_only_when_the_patients_episode_asks(alert, expected):
    body = ScriptedBody()
    pipeline = pipeline_for(body)
    pipeline.admit(0.0, Episode("MRN-1", 0.0, "nurse jo", bed_exit_alert=alert, bed_exit_after_s=120.0))
    events = run(pipeline, body, 30, posture="supine", sacrum=(40.0, 850.0, 450.0))
    events += run(pipeline, body, 5, start=30, posture="out-of-bed")
    assert [e.key for e in events if e.kind == "raised"] == expected
    if alert:
        exit_alarm = next(e for e in events if e.key == "bed-exit")
        assert exit_alarm.time_s == 32 * MIN                       # left at 30 min (settled at 31), plus 2 min


def test_the_pipeline_carries_on_after_a_restart_with_no_alarm_lost_or_repeated():
    def scene(body, m):
        body.lie("supine" if m < 300 else "left-60", sacrum=(SACRUM_MMHG, 850.0 + m % 5, 450.0),
                 **{"heel-left": (45.0, 1790.0, 520.0)})

    body = ScriptedBody()
    whole = pipeline_for(body)
    whole.admit(0.0, Episode("MRN-1", 0.0, "nurse jo"))
    expected = []
    for m in range(9 * 60):
        scene(body, m)
        out = whole.update(frame(m))
        expected += [whole.record(e).to_dict() for e in out.turn_events + out.alarm_events]
    body = ScriptedBody()
    pipeline, got = pipeline_for(body), []
    pipeline.admit(0.0, Episode("MRN-1", 0.0, "nurse jo"))
    for m in range(9 * 60):
        if m % 97 == 13:
            state = json.loads(json.dumps(pipeline.state()))
            pipeline = AlertPipeline.from_state(GRID, state, classify=body.classify, locate=body.locate)
        scene(body, m)
        out = pipeline.update(frame(m))
        got += [pipeline.record(e).to_dict() for e in out.turn_events + out.alarm_events]
    assert got == expected and any(e["kind"] == "raised" and e["site"] == "sacrum" for e in got)
