"""The turn clock on the virtual bed's patients, read as the monitor reads them: turns found, shifts and
skin checks ignored."""

import functools

import numpy as np
import pytest

from appliance.alerts.turns import TurnClock, turn_clock_for
from appliance.core.layouts import get_layout
from appliance.core.pressure_map import PressureMap
from appliance.errors import ConfigError
from appliance.service.config import MonitorConfig
from appliance.service.monitor import Monitor
from appliance.service.virtual_bed import VirtualBedSource
from appliance.sim.scenes import load_scene

BED = get_layout(MonitorConfig().layout)                 # the default bed, which bed_monitoring models


def bed_clock(**settings):
    """The turn clock as the pipeline builds it on the bed: the heels' own movements are no turn, nor is a peak
    moving to the next pixel."""
    from appliance.core.pixels import pixel_grid

    return turn_clock_for(pixel_grid(BED), **settings)


@pytest.fixture(scope="module")
def maps(bed_monitoring):
    """``maps(name, t)``: the monitor's pressure map of scenario ``name`` at scene time ``t`` (cached)."""
    model, calibration = bed_monitoring
    monitors = {}

    @functools.lru_cache(maxsize=None)
    def map_at(name, t):
        if name not in monitors:
            source = VirtualBedSource(BED, load_scene(name), model.setup.protocol, seed=3)
            monitor = Monitor(source.acquire, model, calibration)
            monitor.take_reference(source.empty_reference())
            monitors[name] = (source, monitor)
        source, monitor = monitors[name]
        source.front_end.time_s = float(t)
        return monitor.next_map()

    return map_at


def run(clock, maps, name, times):
    return [event for t in times for event in clock.update(maps(name, t))]


def test_a_30_degree_turn_restarts_the_clock_dated_from_when_it_began(maps):
    clock = bed_clock()                             # supine, turned left at 7200 s over 20 s
    events = run(clock, maps, "turn-schedule", np.arange(0.0, 7600.0, 10.0))
    kinds = [(e.kind, e.time_s) for e in events]
    assert kinds[0][0] == "repositioned" and kinds[0][1] <= 30.0   # lying down starts the clock
    turned = [e for e in events[1:] if e.kind == "repositioned"]
    assert len(turned) == 1 and 7200.0 <= turned[0].time_s <= 7230.0 and turned[0].relieved_share > 0.1
    assert ("turn-due", kinds[0][1] + 7200.0) in kinds             # due two hours after lying down
    assert clock.due_in_s(7590.0) == pytest.approx(turned[0].time_s + 7200.0 - 7590.0)


def test_shifts_of_a_few_centimetres_are_not_turns(maps):
    clock = bed_clock()
    events = run(clock, maps, "restless", np.arange(0.0, 3600.0, 10.0))
    assert [e.kind for e in events] == ["repositioned"]            # only lying down


def test_a_brief_lift_shorter_than_the_settling_time_does_not_count(maps):
    clock = bed_clock(settle_s=60.0)
    lying = maps("supine-still", 3600.0).pressure_kpa
    maps = [(t, lying) for t in range(0, 600, 10)] + [(t, np.zeros_like(lying)) for t in range(600, 640, 10)] \
        + [(t, lying) for t in range(640, 900, 10)]
    events = [e for t, kpa in maps for e in clock.update(PressureMap(float(t), kpa, [], None, 0))]
    assert [(e.kind, e.time_s) for e in events] == [("repositioned", 0.0)]


def test_leaving_the_bed_stops_the_clock_and_coming_back_starts_it(maps):
    clock = bed_clock()                            # out of bed at 3600 s, back at 4500 s
    events = run(clock, maps, "leaves-bed", np.arange(0.0, 4400.0, 10.0))
    assert [e.kind for e in events if e.kind != "turn-due"] == ["repositioned", "bed-empty"]
    assert 3600.0 <= events[-1].time_s <= 3700.0 and clock.bed_empty and clock.due_in_s(4400.0) is None
    back = run(clock, maps, "leaves-bed", np.arange(4400.0, 4800.0, 10.0))
    assert [e.kind for e in back] == ["repositioned"] and 4500.0 <= back[0].time_s <= 4560.0


def test_the_clock_carries_on_after_a_restart_mid_turn(maps):
    times = np.arange(7000.0, 7400.0, 10.0)
    whole = bed_clock()
    run(whole, maps, "turn-schedule", [0.0, 30.0, 60.0, 100.0])
    restarted = bed_clock().restore(whole.state())
    first = run(whole, maps, "turn-schedule", times)
    cut = 24                                                        # mid-turn, the new posture not yet settled
    before = run(restarted, maps, "turn-schedule", times[:cut])
    restarted = bed_clock().restore(restarted.state())
    after = run(restarted, maps, "turn-schedule", times[cut:])
    assert before + after == first and restarted.last_turn_s == whole.last_turn_s


def test_bad_settings_are_refused_by_name():
    with pytest.raises(ConfigError, match="interval 0"):
        TurnClock(interval_s=0)
    with pytest.raises(ConfigError, match="relieved share 1.5"):
        TurnClock(relieved_share=1.5)


def test_a_peak_moved_to_the_next_pixel_is_no_relief_but_one_moved_beyond_reach_is():
    clock = TurnClock(reach_px=1, settle_s=0.0)
    lying = np.zeros((20, 10))
    lying[10, 5] = 8.0                                           # a narrow peak, 60 mmHg
    clock.update(PressureMap(0.0, lying, [], None, 0))
    assert clock.relieved(np.roll(lying, 1, axis=0)) == 0.0
    assert clock.relieved(np.roll(lying, 2, axis=0)) == 1.0
    assert TurnClock(settle_s=0.0).relieved(lying) == 0.0        # no posture held yet


def test_the_reach_spans_a_shift_of_a_few_centimetres_on_the_grids_pixels():
    from appliance.alerts.turns import SHIFT_MM
    from appliance.core.pixels import pixel_grid

    for rows, reach in ((16, 0), (30, 1), (60, 2)):                 # 56, 30 and 15 mm pixels
        grid = pixel_grid(BED, rows=rows)
        assert turn_clock_for(grid).reach_px == reach
        assert (reach + 1) * min(grid.pixel_mm) > SHIFT_MM >= reach * min(grid.pixel_mm)
