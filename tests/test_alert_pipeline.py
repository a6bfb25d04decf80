"""The alert pipeline on the virtual bed, one monitor map per simulated minute: the unturned patient
alarms when the dose crosses its threshold, the turned one does not."""

import json

import numpy as np
import pytest

from appliance.alerts.pipeline import AlertPipeline, AlertSettings
from appliance.core.layouts import get_layout
from appliance.service.config import MonitorConfig
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
    raised, crossing = {}, {}
    for m in unturned:
        frame = pipeline.update(m)
        for region_id, dose in frame.region_doses.items():
            if dose >= 1.0 and region_id not in crossing:
                crossing[region_id] = m.time_s
        for event in frame.alarm_events:
            if event.kind == "raised":
                raised[event.key] = event.time_s
    sacral = {key: t for key, t in raised.items() if key.startswith("pressure:sacrum:")}
    assert sacral, f"no sacral alarm; raised: {raised}"
    for key, t in sacral.items():
        region_id = int(key.rsplit(":", 1)[1])
        assert t == crossing[region_id]                    # the same frame the dose crossed 1
    assert 2 * 3600 <= min(sacral.values()) <= 12 * 3600
    assert "turn:due" in raised and raised["turn:due"] <= 2 * 3600 + 2 * MINUTE


def test_a_patient_turned_every_two_hours_raises_no_pressure_alarm(bed_monitoring):
    model, _ = bed_monitoring
    pipeline = AlertPipeline(model.reconstructor.grid)
    raised, turns = [], []
    for m in monitored(bed_monitoring, "turn-schedule"):
        frame = pipeline.update(m)
        raised += [e.key for e in frame.alarm_events if e.kind == "raised"]
        turns += [e for e in frame.turn_events if e.kind == "repositioned"]
    assert not [key for key in raised if key.startswith("pressure:")]
    assert len(turns) == 4                                 # lying down and three turns


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
    from appliance.core.pressure import KPA_PER_MMHG
    from appliance.core.pressure_map import PressureMap

    model, _ = bed_monitoring
    grid = model.reconstructor.grid
    pipeline = AlertPipeline(grid, AlertSettings())
    loaded = np.zeros(grid.shape)
    loaded[3, 5] = 60 * KPA_PER_MMHG
    pipeline.update(PressureMap(0.0, loaded, [], None, 0))
    pipeline.update(PressureMap(gap_h * 3600, loaded, [], None, 0))
    expected = counted_h * 3600 / pipeline.curve.tolerable_s(loaded)[3, 5]
    assert pipeline.dose.dose[3, 5] == pytest.approx(expected, rel=1e-9)
    assert pipeline.engine.clinical()                                  # the loaded site alarms at once
