"""The alert pipeline on the virtual bed, one monitor map per simulated minute: the unturned patient
alarms when the dose crosses its threshold, the turned one does not."""

import json

import numpy as np
import pytest

from appliance.alerts.pipeline import AlertPipeline, AlertSettings
from appliance.core.named_layouts import get_layout
from appliance.service.config_sections import MonitorConfig
from appliance.service.monitor import Monitor
from appliance.service.virtual_bed import VirtualBedSource
from appliance.sim.scenes import load_scene

BED = get_layout(MonitorConfig().layout)                 # the default bed, which bed_monitoring models
MINUTE = 60.0


def monitored(bed_monitoring, name):
    """The monitor's maps of scenario ``name``, one per simulated minute, from its start to its end."""
    model, calibration = bed_monitoring
    scene = load_scene(name)
    source = VirtualBedSource(BED, scene, model.setup.protocol, seed=5, frame_interval_s=MINUTE)
    monitor = Monitor(source.acquire, model, calibration)
    monitor.take_reference(source.empty_reference())
    while source.front_end.time_s <= scene.duration_s:
        yield monitor.next_map()


@pytest.fixture(scope="module")
def unturned(bed_monitoring):
    return list(monitored(bed_monitoring, "supine-unturned"))


def test_an_unturned_patient_alarms_at_the_sacrum_in_the_frame_the_dose_crosses(unturned, bed_monitoring):
    model, _ = bed_monitoring
    pipeline = AlertPipeline(model.reconstructor.grid)
    raised, crossing, postures = {}, {}, set()
    for m in unturned:
        frame = pipeline.update(m)
        postures.add(frame.posture)
        for site, dose in frame.site_doses.items():
            if dose >= 1.0 and site not in crossing:
                crossing[site] = m.time_s
        for event in frame.alarm_events:
            if event.kind == "raised":
                raised[event.key] = event.time_s
    assert "pressure:sacrum" in raised, f"no sacral alarm; raised: {raised}"
    assert raised["pressure:sacrum"] == crossing["sacrum"]        # the same frame the dose crossed 1
    assert 2 * 3600 <= raised["pressure:sacrum"] <= 12 * 3600
    assert postures <= {"supine", "out-of-bed"}
    assert raised["turn:due"] <= 2 * 3600 + 2 * MINUTE and raised["turn:overdue:1"] <= 2.5 * 3600 + 2 * MINUTE


def test_a_patient_turned_every_two_hours_raises_no_pressure_alarm(bed_monitoring):
    model, _ = bed_monitoring
    pipeline = AlertPipeline(model.reconstructor.grid)
    raised, turns = [], []
    for m in monitored(bed_monitoring, "turn-schedule"):
        frame = pipeline.update(m)
        raised += [e.key for e in frame.alarm_events if e.kind == "raised"]
        turns += [e.kind for e in frame.turn_events]
    assert not [key for key in raised if key.startswith(("pressure:", "turn:overdue"))]
    assert turns == ["lay-down", "repositioned", "repositioned", "repositioned"]


def test_the_pipeline_carries_on_after_a_restart_with_no_alarm_lost_or_repeated(unturned, bed_monitoring):
    model, _ = bed_monitoring
    grid = model.reconstructor.grid
    whole = AlertPipeline(grid)
    expected = [(e.time_s, e.kind, e.key) for m in unturned for e in whole.update(m).alarm_events]
    rng = np.random.default_rng(7)
    cuts = sorted(rng.choice(np.arange(1, len(unturned) - 1), size=5, replace=False))
    pipeline, got, start = AlertPipeline(grid), [], 0
    for cut in list(cuts) + [len(unturned)]:
        for m in unturned[start:cut]:
            got += [(e.time_s, e.kind, e.key) for e in pipeline.update(m).alarm_events]
        state = json.loads(json.dumps(pipeline.state()))        # what a checkpoint on disk holds
        pipeline, start = AlertPipeline.from_state(grid, state), cut
    assert got == expected


def test_a_technical_condition_is_an_alarm_of_its_own_kind(bed_monitoring):
    model, _ = bed_monitoring
    pipeline = AlertPipeline(model.reconstructor.grid, AlertSettings())
    empty = np.zeros(model.reconstructor.grid.shape)
    from appliance.core.pressure_map import PressureMap

    events = pipeline.update(PressureMap(0.0, empty, [], None, 0), {"technical:electrode:5": "electrode 5 open"})
    assert [(e.kind, e.category, e.priority) for e in events.alarm_events] == [("raised", "technical", "medium")]
    assert pipeline.engine.technical() and not pipeline.engine.clinical()
    ended = pipeline.update(PressureMap(1.0, empty, [], None, 0)).alarm_events
    assert [e.kind for e in ended] == ["ended"]


@pytest.mark.parametrize("gap_h, counted_h", [(3.0, 3.0), (30 * 24.0, 12.0)])
def test_a_gap_between_maps_counts_as_the_new_pressure_held_up_to_twelve_hours(bed_monitoring, gap_h, counted_h):
    """A monitor restarted after hours off (or a clock that jumped) carries on: the new map's pressure counts
    for the gap, as any frame's does, up to 12 h."""
    from types import SimpleNamespace

    from appliance.alerts.posture import PostureEstimate
    from appliance.core.pressure import KPA_PER_MMHG
    from appliance.core.pressure_map import PressureMap

    model, _ = bed_monitoring
    grid = model.reconstructor.grid
    kpa = 60 * KPA_PER_MMHG
    sacrum = SimpleNamespace(site="sacrum", along_mm=850.0, across_mm=450.0, peak_kpa=kpa)
    pipeline = AlertPipeline(grid, AlertSettings(), classify=lambda view: PostureEstimate.certain("supine"),
                             locate=lambda view, p: [sacrum])
    loaded = np.zeros(grid.shape)
    pipeline.update(PressureMap(0.0, loaded, [], None, 0))
    pipeline.update(PressureMap(gap_h * 3600, loaded, [], None, 0))
    expected = counted_h * 3600 / pipeline.curve.tolerable_s(kpa)
    assert pipeline.dose.doses()["sacrum"] == pytest.approx(expected, rel=1e-9)
    assert pipeline.engine.clinical()                                  # the loaded site alarms at once
