"""The benchmark scripts stay runnable: each one's pieces run on a small case and report sane numbers."""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from appliance.sim.scenes import PMAT_POSTURE_FILES

BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"


def load(name):
    sys.path.insert(0, str(BENCHMARKS))
    try:
        spec = importlib.util.spec_from_file_location(f"bench_{name}", BENCHMARKS / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = module             # its dataclasses look themselves up there
        spec.loader.exec_module(module)
        return module
    finally:
        sys.path.remove(str(BENCHMARKS))


def test_forward_benchmark_phases():
    forward = load("forward")
    from appliance.core.named_layouts import get_layout

    nodes, build, assemble, factor, solve, total = forward.phase_times(get_layout("grid-4x4"), 0.5)
    assert 300 < nodes < 1500
    assert 0 < assemble < factor and 0 < solve and total < 1.0


@pytest.fixture(scope="module")
def chapter5():
    return load("thesis_chapter5")


def test_chapter5_sweep_and_literal_check_on_phantom_c(chapter5, monkeypatch):
    monkeypatch.setattr(chapter5, "CONTRASTS", np.array([1e-3, 1e3]))
    phantom = chapter5.Phantom("C", "network")
    q, dvv, q_subset, dvv_trimmed = chapter5.sweep(phantom)
    assert q.shape == (7, 2) and np.all(q[:, 0] > 0) and np.all(q[:, 1] < 0)
    assert np.abs(q - q_subset).max() < 1e-9
    assert phantom.nominal_area(10) == pytest.approx(100 / 256)
    dq, ddvv = chapter5.literal_check(phantom, contrasts=(1e-3,))
    assert dq < 1e-4


def test_chapter5_sensitivity_map_peaks_at_the_centre_for_c(chapter5):
    values = chapter5.sensitivity_map(chapter5.Phantom("C", "network"), n=5)
    assert values.shape == (5, 5) and values[2, 2] == np.nanmax(values)


def test_pressure_benchmark_helpers_and_a_small_backprojection_run(monkeypatch):
    pressure = load("pressure")
    from appliance.core.named_layouts import get_layout
    from appliance.core.pixels import pixel_grid
    from appliance.core.pressure_map import loaded_regions
    from appliance.sim.field import PressureField

    grid = pixel_grid(get_layout("grid-4x4"))
    field = PressureField.uniform(100, 100, 10.0).with_square_load(30, 60, 20, 8.0)
    averaged = pressure.pixel_average(field, grid)
    w, h = grid.pixel_mm
    assert averaged.sum() * w * h == pytest.approx(8.0 * 400)       # the force is kept
    regions = loaded_regions(averaged, grid)
    assert pressure.match_regions(regions, regions) == [0.0]
    assert pressure.match_regions(regions, []) == [float("inf")]
    loads = pressure.calibration_loads
    monkeypatch.setattr(pressure, "calibration_loads", lambda layout: loads(layout)[::7])
    results, notes, _ = pressure.single_load_part(1, ("backprojection",), lambda message: None)
    assert not notes
    rows = results["backprojection"]["rows"]
    assert [r["area"] for r in rows] == list(pressure.AREAS_CM2)
    assert all(np.isfinite(r["peak"]) and r["rmse"] >= 0 and r["seconds"] > 0 for r in rows)
    assert results["backprojection"]["iterate"] == "never" and pressure.iterate_for("greit") is None
    for r in rows:
        r["force"] = 1.0
    blur, lumps = pressure.blur_notes(results)
    assert blur.startswith("* backprojection") and lumps
    assert pressure.lumpy(6.2, 25) and pressure.lumpy(13.5, 16) and not pressure.lumpy(24.2, 4)
    from appliance.core.pressure import PressureCurve
    note = pressure.curve_note("greit", PressureCurve(np.array([0.0, 0.1, 0.2, 0.22]), np.array([0.0, 2.0, 5.0, 20.0])))
    assert "0.2 -> 5.0" in note and "1.10 times the change" in note


def test_mismatch_benchmark_runs_a_small_case(monkeypatch):
    mismatch = load("mismatch")
    from appliance.core.named_layouts import get_layout
    from appliance.core.protocols import default_protocol

    monkeypatch.setattr(mismatch, "DRAWS", 1)
    monkeypatch.setattr(mismatch, "LOADS", 4)
    monkeypatch.setattr(mismatch, "TRUTH_DENSITY", 1.5)
    layout = get_layout("grid-4x4")
    protocol = default_protocol(layout)
    nominal, fitting = mismatch.models(layout, protocol)
    case = mismatch.CASES[4]                                  # the saline mat: contacts the readings determine
    result = mismatch.run_case(case, layout, protocol, nominal, fitting)
    assert all(0 <= result[key][0] < 5 for key in ("image_before", "image_after", "region_before", "region_after"))
    fit = result["fits"][0]
    assert fit["accepted"] and fit["determined"] >= 8 and abs(fit["sheet"] - 1) < 0.05
    row = mismatch.case_rows([(case, result)])[0]
    assert row[0] == case.name and row[1] == 4


def test_bed_benchmark_spots_sites_tilts_and_nights():
    bed = load("bed")
    from appliance.core.named_layouts import get_layout
    from appliance.core.pixels import pixel_grid

    truth = np.zeros((30, 64))
    truth[14:16, 2:4] = [[60.0, 50.0], [45.0, 38.0]]       # the head
    truth[12:18, 24:34] = 30.0                               # the back, under 32 mmHg: no spot
    truth[10:12, 58:60] = 41.0                               # a heel
    truth[18:20, 58:60] = 35.0                               # a heel under 40 mmHg at its peak: no spot
    read = np.zeros_like(truth)
    read[15, 4] = 45.0                                       # the head read one pixel off, 25 % low
    spots = bed.spots_of(truth, read, 4, 1)
    spots = sorted(spots, key=lambda s: s.site)
    assert [(s.site, s.true_mmhg, s.read_mmhg, s.seen) for s in spots] == [("head", 60.0, 45.0, True),
                                                                         ("heels", 41.0, 0.0, False)]
    assert spots[0].error == -0.25
    summary = bed.summary(spots)
    assert summary["spots"] == 2 and summary["seen"] == 0.5 and summary["median_abs_error"] == 0.625

    grid = pixel_grid(get_layout("grid-8x16"), 16, 34)
    coarse = np.arange(16 * 34, dtype=float).reshape(16, 34)
    fine = bed.on_pixels(coarse, grid, (30, 64))
    assert fine.shape == (30, 64) and fine.max() == coarse.max() and fine[0, 0] == 0.0

    supine = np.zeros((30, 64))
    supine[14:16, 20:40] = 40.0
    right = np.zeros((30, 64))
    right[8:10, 20:40] = 40.0
    left = np.zeros((30, 64))
    left[20:22, 20:40] = 40.0
    maps = {(4, 1): (supine, supine), (4, 4): (right, right), (4, 6): (right, left)}     # 6 read to the wrong side
    assert bed.tilts_told_apart(maps) == (1, 2)

    loaded = np.zeros((30, 64))
    loaded[14:16, 30:32] = 80.0
    maps = {(s, 1): (loaded, np.zeros_like(loaded)) for s in bed.HELD_OUT}
    alarms = bed.night_alarms([(1, 8.0)], maps, bed.HELD_OUT[0], 0, pixel_grid(get_layout("grid-16x32")))
    assert alarms and alarms[0][0] < 8 * 3600, "80 mmHg for 8 h alarms"
    assert bed.night_alarms([(1, 8.0)], maps, bed.HELD_OUT[0], 1, pixel_grid(get_layout("grid-16x32"))) == []


@pytest.mark.slow
def test_the_default_bed_sees_a_person_it_was_never_calibrated_on(bed_monitoring):
    """The appliance's own model and shipped calibration, through the parallel board, on S11's 17 postures
    (S11 is in no fit): the bed benchmark's must-hold figures, on one person."""
    bed = load("bed")
    model, calibration = bed_monitoring
    assert calibration.notes["kind"] == "maps", "the package's calibration, made from people's maps"
    assert not [name for name in calibration.notes["maps"] if name.startswith(tuple(f"S{s}/" for s in bed.HELD_OUT))]
    spots, maps, _ = bed.read_held_out(model, calibration, bed.RecordedMat(bed.Mat(model.setup.layout.name)),
                                       subjects=(11,))
    summary = bed.summary(spots)
    assert summary["spots"] >= 40
    assert summary["seen"] >= 0.95 and summary["median_abs_error"] <= 0.25, summary
    assert bed.tilts_told_apart(maps) == (2, 2)


def test_alerts_benchmark_nights_and_scoring():
    alerts = load("alerts")
    nights = alerts.nights()
    assert {n.subject for n in nights} == {4, 6, 11}                     # held-out subjects only
    hours = sorted({(n.name, n.duration_s / 3600) for n in nights})
    assert [h for _, h in hours] == [8.0, 4.0, 12.0, 8.0]
    restless = next(n for n in nights if n.name.startswith("restless"))
    assert all(p in (1, 8, 9) and abs(dx) <= 40 and abs(dy) <= 30 for p, _, (dx, dy) in restless.segments)
    assert restless.segment_at(0.0) == (restless.segments[0][0], restless.segments[0][2])
    got = alerts.compare({"sacrum": 100.0, "heel-left": 500.0}, {"sacrum": 160.0, "occiput": 50.0})
    assert got == {"truth": 2, "missed": ["heel-left"], "late_s": [60.0], "false": ["occiput"]}


def test_training_nights_benchmark_holds_the_training_subjects_nights_and_scores_them_as_alerts_does():
    training = load("training_nights")
    nights = training.nights(training.TRAINING_SUBJECTS, training.ON_THE_RIGHT)
    assert {n.subject for n in nights} == {1, 2, 3, 5, 7, 8, 9, 10}       # never a held-out subject
    sides = {n.subject: n.segments[0][0] for n in nights if n.name.startswith("side")}
    right, left = PMAT_POSTURE_FILES["right-90"], PMAT_POSTURE_FILES["left-90"]
    assert sides == {k: right if k in (2, 8, 10) else left for k in sides}
    totals = {"true": {"truth": 4, "missed": 1, "late_s": [0.0, 60.0, 600.0], "false": 1, "hours": 48.0},
              "chain": {"truth": 4, "missed": 0, "late_s": [-120.0, 300.0, 300.0, 900.0], "false": 3, "hours": 48.0}}
    assert training.summary_rows(totals) == [["the true maps", 4, 1, "+1", "10", 1, "0.50"],
                                             ["the whole chain", 4, 0, "+5", "15", 3, "1.50"]]


def test_contact_capacitance_benchmark_compares_the_detectors(monkeypatch):
    bench = load("contact_capacitance")
    monkeypatch.setattr(bench, "CAPACITANCES_F", (0.0, 1e-8))
    monkeypatch.setattr(bench, "BOARDS", {"reference": {}})
    body = bench.run()
    rows = [line.split(" | ") for line in body.splitlines() if line.startswith("| 10 |")]
    assert len(rows) == 1
    rms_change, in_phase_change = float(rows[0][3]), float(rows[0][5])
    assert rms_change > 20 * in_phase_change, body


def test_calibration_cost_counts_the_mechanics_factorisations_and_replays_them_exactly(monkeypatch):
    """A calibration-like run (maps in turn on the bed mat, each from the last one's deflection): a factorisation
    per Newton step with the direct solver, counted where it is made; with multigrid only the grid's own two
    and a small coarsest-level Cholesky a step. The replay finds the recorded deflections with both."""
    from appliance.sim import mechanics
    from appliance.sim.bed import BED_MAT_PARAMETERS

    bench = load("calibration_cost")
    rows, cols = np.mgrid[0:40, 0:20]
    fields = [np.where((rows - r) ** 2 + (cols - c) ** 2 < 30, kpa, 0.0) for r, c, kpa in
              ((12, 8, 6.0), (14, 9, 8.0), (26, 11, 5.0), (20, 10, 40.0), (21, 10, 0.5), (8, 6, 12.0))]
    counts, solves = {}, []
    for solver in bench.SOLVERS:
        mechanics._bordered_system.cache_clear()
        start = None
        with bench.Counted() as counted:
            for field in fields:
                deflection = mechanics.solve_deflection(BED_MAT_PARAMETERS, field, 10.0, start_mm=start,
                                                        solver=solver)
                if solver == "direct":
                    solves.append((BED_MAT_PARAMETERS, field, 10.0, None, start, deflection))
                start = deflection[0]
        counts[solver] = counted
    direct, multigrid = counts["direct"], counts["multigrid"]
    assert direct.calls["mechanics.py:solve"] == direct.steps >= 3 * len(fields)    # several Newton steps a field
    assert direct.calls["mechanics.py:_bordered_system"] == 2 and direct.setups == direct.iterations == 0
    assert bench.mechanics_factorisations(multigrid.calls) == 2, multigrid.calls     # the grid's, once
    assert multigrid.calls["multigrid.py:preconditioner"] == multigrid.steps and multigrid.setups == 1
    assert multigrid.iterations >= 2 * multigrid.steps
    monkeypatch.setattr(bench, "REPEATS", 1)
    replayed = bench.replay(solves)
    assert bench.mechanics_factorisations(replayed["direct"][0].calls) == replayed["direct"][0].steps
    assert bench.mechanics_factorisations(replayed["multigrid"][0].calls) == 0      # the grid is set up already
    assert replayed["direct"][2] == 0.0 and replayed["multigrid"][2] < 1e-9


def test_memory_benchmark_night_changes_electrodes_in_turn_and_its_control_has_no_faults(tmp_path):
    memory = load("memory")
    from appliance.sim.scenes import load_scene

    scenes = {}
    for faults in (True, False):
        path = tmp_path / f"night-{faults}.toml"
        path.write_text(memory.night_scenario(faults), encoding="utf-8")
        scenes[faults] = load_scene(str(path))
    assert scenes[True].duration_s == scenes[False].duration_s == memory.NIGHT_H * 3600
    assert len(scenes[False].faults) == 0
    out = [f.electrode for f in scenes[True].faults if not f.connected]
    assert len(set(out)) == 24 and out.count(memory.FLICKER) == 14    # 23 spells' electrodes; 256 twice in 7
    assert len(scenes[True].faults) == 73


def test_hospital_transport_benchmark_runs_a_small_case(tmp_path):
    """Both paths on a real three-node engine: nothing is confirmed without a quorum, every natively confirmed
    alarm is in the ward's stream once across a leader's kill, and the report carries the figures."""
    bench = load("hospital_transport")
    out = tmp_path / "report.md"
    bench.main(["--alarms", "20", "--probe", "2", "--kill-alarms", "20", "--kill-rounds", "1", "--out", str(out),
                "--dir", str(tmp_path / "engine")])
    text = out.read_text()
    assert "| MQTT QoS 1 | 0 of 2 |" in text and "| native JetStream | 0 of 2 |" in text
    rows = {line.split(" | ")[0]: line.split(" | ") for line in text.splitlines()
            if line.startswith(("| mqtt", "| native"))}
    assert rows["| mqtt"][3] == "20" and 0 <= int(rows["| mqtt"][4]) <= 20      # the listener may lose some
    assert rows["| native"][3:6] == ["20", "0", "0"]                            # the native path never does
    healthy = [line for line in text.splitlines() if line.startswith(("| MQTT 3.1.1", "| native JetStream publish"))]
    assert len(healthy) == 2 and all(line.endswith("| 20 |") for line in healthy)   # every alarm stored


def test_posture_benchmark_measures_how_wide_a_body_touches_the_mat():
    posture = load("posture")
    from appliance.alerts.anatomy import BodyView

    def body(across_cells: int, head_cells: int = 4) -> BodyView:
        kpa = np.zeros((64, 30))
        kpa[12:50, 15 - across_cells // 2:15 + across_cells // 2] = 3.0       # the trunk
        kpa[2:8, 15 - head_cells // 2:15 + head_cells // 2] = 4.0               # the head, narrower
        kpa[52:60, 14:16] = 0.2                                                  # legs under the load floor
        return BodyView(kpa, (30.0, 30.0), True)

    assert posture.contact_width_mm(body(20)) == pytest.approx(600.0)
    assert posture.contact_width_mm(body(10)) == pytest.approx(300.0)
    assert posture.contact_width_mm(BodyView(np.zeros((64, 30)), (30.0, 30.0), True)) == 0.0
    sides = list(posture.SIDE_POSTURES)
    views = {1: ([body(w) for w in (16, 12, 8, 20, 14, 10)], sides),
             2: ([body(w) for w in (12, 12, 10, 18, 16, 8)], sides)}
    rows = posture.width_rows(views)
    assert rows[0] == ["S1", "480", "360", "240", "600", "420", "300"]
    assert rows[-1] == ["median", "420", "360", "270", "570", "450", "270"]


def test_calibration_curve_benchmark_counts_places_read_loaded_where_nothing_is():
    curves = load("calibration_curve")
    truth = np.zeros((10, 20))
    truth[2:5, 2:5] = 45.0                              # a real load
    truth[7, 15] = 27.0                                  # a light one, under 28 mmHg
    read = truth.copy()
    read[7, 15] = 40.0                                   # read over the threshold: a false spot
    read[8, 2] = 33.0                                    # load read where there is none at all
    read[3, 3] = 60.0                                    # a real load read high is no false spot
    assert curves.false_spots(read, truth) == 2
    assert curves.false_spots(truth, truth) == 0


def test_calibration_curve_benchmark_learns_each_pixels_gain_from_maps():
    """Maps read through a mat whose pixels read high and low by turns (as the bed's image does, at its electrode
    pitch): the flat field the benchmark studies finds that pattern, and reads the maps back far closer."""
    curves = load("calibration_curve")
    rng = np.random.default_rng(3)
    rows, cols = np.indices((12, 24))
    gain = np.where((rows + cols) % 2 == 0, 1.3, 0.77)
    maps = {}
    for k in range(60):                                  # bodies of blobs, 0 to about 12 kPa
        truth = np.zeros((12, 24))
        for _ in range(4):
            r, c, w = rng.uniform(0, 12), rng.uniform(0, 24), rng.uniform(1.5, 4.0)
            truth += rng.uniform(2, 8) * np.exp(-((rows - r) ** 2 + (cols - c) ** 2) / (2 * w * w))
        maps[(1, k)] = (-0.05 * truth ** 0.8 * gain, truth)   # a monotone mat, each pixel's gain on top
    with_flat = curves.fitted("matched", maps, [1], None, None, flat_rounds=2)
    without = curves.fitted("matched", maps, [1], None, None)
    assert without[2] is None and np.corrcoef(np.log(with_flat[2]).ravel(), np.log(gain).ravel())[0, 1] > 0.98
    truths = np.array([truth for _, truth in maps.values()])
    loaded = truths > 2.0

    def error(fit):
        read = np.array([curves.read_kpa(fit, image) for image, _ in maps.values()])
        return np.median(np.abs(read[loaded] / truths[loaded] - 1))

    assert error(with_flat) < 0.05 < 0.15 < error(without)
