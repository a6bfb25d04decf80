"""The monitor: frames to pressure maps on the virtual bed, faults survived, foreign calibrations refused."""

import numpy as np
import pytest

from appliance.cli import main
from appliance.core.model_cache import ModelSetup, cached_model
from appliance.core.named_layouts import get_layout
from appliance.core.pressure import load_pressure_calibration, save_pressure_calibration
from appliance.core.protocols import default_protocol
from appliance.errors import ConfigError
from appliance.service.config_sections import MonitorConfig
from appliance.service.live import read_live
from appliance.service.monitor import Monitor
from appliance.service.virtual_bed import VirtualBedSource
from appliance.sim.loads import square_load_scene
from appliance.sim.scenes import load_scene
from appliance.store import Store

GRID = get_layout("grid-4x4")
BED = get_layout(MonitorConfig().layout)


@pytest.fixture(scope="module")
def small_mat(small_mat_calibration):
    """grid-4x4 with a 40 mm weight of 12 kPa on it, and its calibration."""
    model, calibration = small_mat_calibration
    source = VirtualBedSource(GRID, square_load_scene(100, 100, 30, 70, 40, 12.0), default_protocol(GRID), seed=4)
    return model, source, calibration


def test_the_monitor_maps_a_weight_where_it_lies(small_mat):
    model, source, calibration = small_mat
    monitor = Monitor(source.acquire, model, calibration)
    monitor.take_reference(source.empty_reference())
    maps = [monitor.next_map() for _ in range(2)]
    region = maps[-1].regions[0]
    assert np.hypot(region.x_mm - 30, region.y_mm - 70) < 6
    assert 8.0 < maps[-1].peak_kpa < 16.0
    assert maps[1].time_s - maps[0].time_s == pytest.approx(1.0)
    assert maps[-1].usable_readings > 0.9 * len(default_protocol(GRID))


def test_a_calibration_for_another_mat_is_never_loaded(small_mat, tmp_path):
    model, source, calibration = small_mat
    bigger = get_layout("grid-4x4@120x120")
    with pytest.raises(ConfigError, match="made for layout 'grid-4x4'"):
        Monitor(source.acquire, cached_model(ModelSetup(bigger, default_protocol(bigger)), tmp_path)[0],
                calibration)


def test_the_monitor_needs_a_reference_first(small_mat):
    model, source, calibration = small_mat
    with pytest.raises(ConfigError, match="no reference frame"):
        Monitor(source.acquire, model, calibration).next_map()


@pytest.fixture(scope="module")
def bed_run(tmp_path_factory, model_cache):
    """A fresh data directory for ``appliance run``, and the session's model cache."""
    return tmp_path_factory.mktemp("data"), model_cache


def test_run_starts_on_the_virtual_bed_calibrates_once_and_maps_the_patient(bed_run, capsys):
    data, cache = bed_run
    args = ["run", "--frames", "3", "--interval", "60", "--speed", "0", "--scenario", "supine-still",
            "--data-dir", str(data),
            "--cache-dir", str(cache)]
    assert main(args) == 0
    out, err = capsys.readouterr()
    assert "virtual bed (grid-16x32" in err and "pressure calibration" in err
    maps = [line for line in out.strip().splitlines() if not line.startswith("  ")]
    assert len(maps) == 3 and all("region(s) >= 32 mmHg" in line for line in maps)
    assert "  TURN lay-down at 60 s" in out                             # the patient lay down: the clock starts
    with Store.open(data / "appliance.db") as store:
        assert [e["kind"] for e in store.events_since(0.0)] == ["lay-down"]
        assert store.load_state("alerts")["last_time_s"] == 120.0
    newest = np.array(read_live(data / "live.json")["map"]["mmhg"], dtype=float)
    assert newest.shape == (30, 64) and np.nanmax(newest) > 32       # a supine patient loads the sacrum
    assert sorted(p.name for p in data.glob("live.*")) == ["live.json"]  # no per-frame files nothing reads
    assert main(args) == 0                                               # the second start reuses it
    assert "loaded from" in capsys.readouterr().err


def test_run_refuses_a_calibration_made_for_another_layout(bed_run, tmp_path, capsys, small_mat):
    data, cache = bed_run
    _, _, calibration = small_mat
    foreign = tmp_path / "grid-4x4.json"
    save_pressure_calibration(foreign, calibration)
    code = main(["run", "--frames", "1", "--speed", "0", "--scenario", "supine-still", "--data-dir", str(data),
                 "--cache-dir", str(cache), "--calibration", str(foreign)])
    assert code != 0
    assert "made for layout 'grid-4x4', not for 'grid-16x32'" in capsys.readouterr().err
    assert load_pressure_calibration(foreign).layout_name == "grid-4x4"  # the file is left as it was


def test_a_moving_patient_is_solved_again_every_frame_and_mapped(bed_monitoring):
    """Sensor mechanics, forward model, analogue chain, reconstruction and pressure map, a moving patient
    (what a frame costs is in benchmarks/simulator.md)."""
    model, calibration = bed_monitoring
    scene = load_scene("restless")
    source = VirtualBedSource(BED, scene, model.setup.protocol, seed=1, frame_interval_s=0.5)
    monitor = Monitor(source.acquire, model, calibration, adaptive=source.adaptive)
    monitor.take_reference(source.empty_reference())
    moving = [t for t in np.arange(0.0, scene.duration_s - 0.5, 0.5) if scene.changes(t, t + 0.5)][:5]
    assert len(moving) == 5
    totals = []
    for t in moving:
        source.front_end.time_s = t
        solves = source.bed.solves
        totals.append(np.nansum(monitor.next_map().pressure_kpa))
        assert source.bed.solves == solves + 1                           # the patient moved: a full re-solve
    assert totals[-1] > totals[0] + 10.0, "the patient lying down is read as they settle"


def test_the_frame_a_patient_lies_down_in_is_read_whole_and_then_finely_around_them(bed_monitoring):
    model, calibration = bed_monitoring
    source = VirtualBedSource(BED, load_scene("supine-unturned"), model.setup.protocol, frame_interval_s=60.0)
    passes = []

    def acquire(loaded=None):
        passes.append(loaded)
        return source.acquire(loaded=loaded)

    monitor = Monitor(acquire, model, calibration, adaptive=source.adaptive)
    monitor.take_reference(source.empty_reference())
    maps = [monitor.next_map() for _ in range(3)]                 # the empty mat at 0 s, lying down by 60 s
    assert source.adaptive and not maps[0].regions
    assert passes[:2] == [None, None] and len(passes[2]) > 0      # whole, whole, then finely around the body
    assert len(maps[1].regions) <= 2 * len(maps[2].regions)      # no scattered peaks from the empty mat's readings


def test_an_electrode_lost_mid_run_is_a_technical_alarm_and_monitoring_goes_on(small_mat):
    from appliance.alerts.pipeline import AlertPipeline, technical_alarms

    model, source, calibration = small_mat
    monitor = Monitor(source.acquire, model, calibration)
    monitor.take_reference(source.empty_reference())
    pipeline = AlertPipeline(model.reconstructor.grid)
    raised, maps = [], []
    for frame in range(6):
        if frame == 3:
            source.front_end.disconnect(6)
        m = monitor.next_map()
        maps.append(m)
        events = pipeline.update(m, technical_alarms(monitor.conditions)).alarm_events
        raised += [(frame, e.key, e.category) for e in events if e.kind == "raised"]
    assert raised == [(3, "technical:electrode:6", "technical")]          # the first frame without it
    assert maps[-1].usable_readings < maps[2].usable_readings
    region = maps[-1].regions[0]                                           # the weight is still seen
    assert np.hypot(region.x_mm - 30, region.y_mm - 70) < 8
    with pytest.raises(ValueError, match="electrode 17 is not on this 16-electrode mat"):
        source.front_end.disconnect(17)
    source.front_end.open_electrodes.clear()                               # the mat is shared by the module


def test_the_monitor_returns_freed_memory_to_the_system_every_so_many_maps(small_mat, monkeypatch):
    import appliance.service.monitor as monitor_module

    model, source, calibration = small_mat
    calls = []
    monkeypatch.setattr(monitor_module, "RETURN_MEMORY_FRAMES", 2)
    monkeypatch.setattr(monitor_module, "return_freed_memory", lambda: calls.append(monitor.maps_made))
    monitor = Monitor(source.acquire, model, calibration)
    monitor.take_reference(source.empty_reference())
    for _ in range(5):
        monitor.next_map()
    assert calls == [2, 4]


def test_the_monitor_factorises_its_reconstructor_when_the_reference_is_set(small_mat, monkeypatch):
    import appliance.core.reconstruct as reconstruct
    from appliance.core.model_cache import build_model

    model, source, calibration = small_mat
    monkeypatch.setattr(reconstruct, "DENSE_LIMIT", 0)
    factored = build_model(model.setup)                                    # kept as its factors, as a bed's
    form = factored.reconstructor.normal_form
    del form.__dict__["solve"]                                             # as a model loaded from the cache
    monitor = Monitor(source.acquire, factored, calibration)
    assert "solve" not in form.__dict__
    monitor.take_reference(source.empty_reference())
    assert "solve" in form.__dict__                                        # not left to the first frame
