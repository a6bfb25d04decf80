"""The virtual bed as the front end's sensor, and the calibration procedures run on it."""

import numpy as np
import pytest

from appliance.calibration import (KPA_PER_GRAM_PER_CM2, Load, calibration_loads, grams_for, pressure_calibration,
                                   sensitivity_calibration, thesis_loads)
from appliance.core.frames import load_calibration
from appliance.core.model_cache import ModelSetup, cached_model
from appliance.core.named_layouts import get_layout
from appliance.core.pressure import layout_fingerprint
from appliance.core.pressure_map import loaded_regions
from appliance.core.protocols import default_protocol
from appliance.drivers.backend import open_board, open_front_end
from appliance.drivers.scan import ScanEngine
from appliance.errors import ConfigError, ModelInputInvalid
from appliance.sim.bed import VirtualBed
from appliance.sim.field import PressureField
from appliance.sim.frontend import VIRTUAL_MAT_BOARD, VirtualFrontEnd
from appliance.sim.loads import StaticScene, empty_mat, placer, square_load_scene, square_loads_read_back
from appliance.sim.scenes import load_scene

GRID = get_layout("grid-4x4")
PROTOCOL = default_protocol(GRID)


def empty_bed(**options):
    return VirtualBed(GRID, empty_mat(GRID), **options)


def test_a_still_scene_is_solved_once_and_a_new_scene_or_temperature_is_solved_again():
    temperature = {"c": 24.0}
    bed = empty_bed(temperature_c=lambda t: temperature["c"])
    first = bed.transfer_ohm(0.0)
    assert bed.transfer_ohm(50.0) is first and (bed.solves, bed.reuses) == (1, 1)
    placer(bed)(Load(50, 50, 30, 10.0))
    pressed = bed.transfer_ohm(60.0)
    assert bed.solves == 2
    assert np.abs(pressed - first).max() > 1e-3 * np.abs(first).max()
    temperature["c"] = 26.0
    warmer = bed.transfer_ohm(70.0)
    assert bed.solves == 3
    # saline conducts about 2 % more per degree: transfer impedances fall by about that
    assert np.median(warmer[first != 0] / pressed[first != 0]) == pytest.approx(1 / 1.04, abs=0.01)


def test_a_moving_scene_is_solved_again_only_when_it_moves():
    bed = VirtualBed(get_layout("grid-8x16"), load_scene("turn-schedule"), density=0.25, mechanics_merge=5)
    bed.transfer_ohm(10.0)
    bed.transfer_ohm(11.0)                     # lying still between turns
    assert (bed.solves, bed.reuses) == (1, 1)
    turn = next(t for t in np.arange(11.0, bed.scene.duration_s, 30.0) if bed.scene.changes(11.0, t))
    bed.transfer_ohm(turn)
    assert bed.solves == 2


def test_a_mat_brought_back_to_a_moment_remembers_its_loading_as_if_read_all_along():
    def bed():
        return VirtualBed(get_layout("grid-8x16"), load_scene("turn-schedule"), density=0.25, mechanics_merge=5)

    times = [0.0, 60.0, 600.0, 7200.0, 7210.0, 7800.0]          # lying down, then turned 30 degrees at 7200 s
    continuous = bed()
    for t in times:
        continuous.transfer_ohm(t)
    resumed, fresh = bed(), bed()
    resumed.remember(times)
    later = [continuous.transfer_ohm(8400.0), resumed.transfer_ohm(8400.0), fresh.transfer_ohm(8400.0)]
    scale = np.abs(later[0]).max()
    assert np.abs(later[1] - later[0]).max() < 1e-9 * scale
    assert np.abs(later[2] - later[0]).max() > 1e-6 * scale    # freshly loaded, the play sits elsewhere


def test_a_portrait_scene_is_turned_onto_a_landscape_bed_and_a_wrong_size_is_refused():
    scene = load_scene("supine-still")          # head to foot along its y
    bed = VirtualBed(get_layout("grid-8x16"), scene, density=0.25, mechanics_merge=5)
    field = bed.field_at(0.0)
    assert field.size_mm == pytest.approx(get_layout("grid-8x16").sheet.size_mm)
    assert field.peak_kpa == pytest.approx(scene.pressure_at(0.0).peak_kpa)
    with pytest.raises(ModelInputInvalid, match="does not fit layout 'grid-4x4'"):
        VirtualBed(GRID, scene)


def test_loads_outside_the_mat_and_negative_pressure_are_refused():
    with pytest.raises(ModelInputInvalid, match="outside"):
        square_load_scene(100, 100, 95, 50, 30, 5.0)
    with pytest.raises(ModelInputInvalid, match="negative"):
        StaticScene(PressureField(-np.ones((5, 5)), 2.0))


def test_the_front_end_reads_the_bed_through_the_analogue_chain_and_keeps_scene_time():
    bed = empty_bed()
    front = VirtualFrontEnd(bed, PROTOCOL, seed=3, frame_interval_s=2.0)
    first, second = front.acquire(), front.acquire()
    assert (first.time_s, second.time_s) == (0.0, 2.0)
    ideal = front.chain.ideal(bed.transfer_ohm(0.0), PROTOCOL)
    assert first.volts.shape == (len(PROTOCOL),) and np.isfinite(first.volts).all()
    assert np.abs(first.volts - second.volts).max() > 0          # fresh noise each frame
    accuracy = front.chain.profile.accuracy
    assert np.abs(first.volts - second.volts).max() < 4 * (accuracy.relative * np.abs(first.volts).max()
                                                             + accuracy.absolute_v)
    assert first.temperature_c == 24.0
    assert np.allclose(first.volts, ideal, rtol=0.02, atol=4 * accuracy.absolute_v)
    with pytest.raises(ValueError, match="16-electrode mat"):
        VirtualFrontEnd(bed, default_protocol(get_layout("grid-8x16")))


def test_the_emulated_chips_can_measure_the_virtual_bed():
    bed = empty_bed()
    placer(bed)(Load(30, 70, 30, 8.0))
    board, profile = open_board({"backend": "emulated", **VIRTUAL_MAT_BOARD}, sensor=lambda: bed, seed=2)
    frame = ScanEngine(open_front_end(board, profile), PROTOCOL).scan()
    expected = VirtualFrontEnd(bed, PROTOCOL).chain.ideal(bed.transfer_ohm(0.0), PROTOCOL)
    measured = np.isfinite(frame.volts)             # the heaviest-pressed readings saturate, as on a bench
    assert measured.sum() >= 0.95 * len(PROTOCOL)
    assert np.allclose(frame.volts[measured], expected[measured], rtol=0.01, atol=1e-5)


def test_calibration_loads_follow_the_thesis_weights_and_scale_with_the_mat():
    assert thesis_loads(100, 100, areas_cm2=(4.0,), positions=1, weights_g=(100,))[0].pressure_kpa == \
        pytest.approx(2.45, abs=0.01)                                         # Table 6.3.1
    loads = calibration_loads(GRID)
    assert sorted({round(l.side_mm ** 2 / 100) for l in loads}) == [9, 16, 25]
    assert {l.pressure_kpa for l in loads} == {2.0, 3.5, 5.0, 7.5, 10.0, 14.0, 20.0}
    assert grams_for(Load(50, 50, 20, 2.45)) == pytest.approx(2.45 * 4 / KPA_PER_GRAM_PER_CM2)
    bed_loads = calibration_loads(get_layout("grid-8x16"))
    assert min(l.side_mm for l in bed_loads if l.zone is None) > 100          # scaled to 120 mm electrodes
    assert {l.side_mm for l in bed_loads if l.zone == "foot-end"} == {50.0}     # and heel-size at the foot end
    for load in bed_loads:
        assert load.side_mm / 2 <= load.x_mm <= 1900 - load.side_mm / 2
        assert load.side_mm / 2 <= load.y_mm <= 900 - load.side_mm / 2


def test_a_load_covers_pixels_by_the_share_it_overlaps():
    grid = cached_grid()
    pressure = Load(50.0, 50.0, 30.0, 4.0).pixel_pressure(grid)
    w, h = grid.pixel_mm
    assert pressure.sum() * w * h == pytest.approx(4.0 * 30 * 30)
    assert pressure.max() == 4.0


def cached_grid():
    from appliance.core.pixels import pixel_grid
    return pixel_grid(GRID)


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """grid-4x4 calibrated on the virtual bed with the default loads; the bed and model kept for use."""
    model, _ = cached_model(ModelSetup(GRID, PROTOCOL), tmp_path_factory.mktemp("models"))
    bed = empty_bed()
    front = VirtualFrontEnd(bed, PROTOCOL, seed=1)
    seen = []
    calibration = pressure_calibration(front.acquire, placer(bed), model, calibration_loads(GRID),
                                       progress=lambda k, n, load: seen.append((k, n)))
    return model, bed, front, calibration, seen


def test_pressure_calibration_reports_progress_and_is_tied_to_its_layout(calibrated):
    model, bed, _, calibration, seen = calibrated
    assert seen[0] == (1, 105) and seen[-1] == (105, 105)
    assert calibration.layout_sha256 == layout_fingerprint(GRID)
    assert bed.scene.pressure_at(0.0).peak_kpa == 0.0                         # the mat is left empty
    assert np.all(np.diff(calibration.curve.pressure) >= 0) and calibration.curve.pressure[-1] >= 19.0
    assert calibration.flat_field is not None and np.exp(np.log(calibration.flat_field).mean()) == pytest.approx(1.0)
    calibration.check_fits(GRID, model.setup.options.algorithm, model.reconstructor.grid.shape)
    with pytest.raises(ConfigError, match="made for layout 'grid-4x4', not for 'square-16'"):
        calibration.check_fits(get_layout("square-16"), model.setup.options.algorithm, (16, 16))


@pytest.mark.parametrize("area_cm2", [9, 16, 25])
def test_square_loads_anywhere_read_their_peak_within_20_percent_and_centre_within_3_mm(calibrated, area_cm2):
    model, bed, front, calibration, _ = calibrated
    peak_errors, centre_errors = square_loads_read_back(model, calibration, front, placer(bed), area_cm2,
                                                        seed=area_cm2)
    assert np.median(np.abs(peak_errors)) <= 0.20
    assert np.median(centre_errors) <= 3.0


def test_regions_above_32_mmhg_are_found_where_loads_press(calibrated):
    model, bed, front, calibration, _ = calibrated
    place = placer(bed)
    place(None)
    reference = front.acquire().volts
    place(Load(30, 30, 40, 12.0))
    image, _ = model.reconstruct(front.acquire().volts, reference, iterate="always")
    place(None)
    regions = loaded_regions(calibration.pressure_kpa(image), model.reconstructor.grid)
    assert regions and np.hypot(regions[0].x_mm - 30, regions[0].y_mm - 30) < 6
    assert 4 < regions[0].area_cm2 < 40 and regions[0].peak_mmhg > 32


def test_sensitivity_calibration_gives_a_file_the_reconstruction_reads(tmp_path):
    from appliance.core.frames import FRAME_HEADER
    from appliance.core.pixels import pixel_grid

    grid = pixel_grid(GRID, 4, 4)
    bed = empty_bed(density=0.5)
    front = VirtualFrontEnd(bed, PROTOCOL, seed=0)
    place = placer(bed)
    rows = sensitivity_calibration(front.acquire, place, grid, PROTOCOL, side_mm=20.0, pressure_kpa=8.0)
    assert len(rows) == 16 * len(PROTOCOL)
    path = tmp_path / "calibration.csv"
    path.write_text(",".join(("pixel_row", "pixel_col") + FRAME_HEADER) + "\n"
                    + "\n".join(",".join(str(v) for v in row) for row in rows) + "\n")
    place(None)
    reference = front.acquire().volts
    sensitivity = load_calibration(path, PROTOCOL, grid, reference)
    assert sensitivity.shape == (16, len(PROTOCOL))
    # a press under pixel (1, 2) changes the readings most like that pixel's calibration row
    place(Load(float(grid.centres_mm[6][0]), float(grid.centres_mm[6][1]), 20.0, 8.0))
    change = front.acquire().volts - reference
    similarity = (sensitivity @ change) / np.linalg.norm(sensitivity, axis=1)
    assert int(np.argmax(np.abs(similarity))) == 6


def test_the_bed_mat_can_be_read_through_the_parallel_front_end():
    from appliance.core.protocols import protocol_for
    from appliance.drivers.profile import board_profile
    from appliance.errors import ProtocolInvalid

    layout = get_layout("grid-16x32")
    bed = VirtualBed(layout, load_scene("supine-still"), density=0.25, mechanics_merge=5)
    protocol = protocol_for(layout, "rows", reach=2)
    profile = board_profile({"profile": "parallel"})
    front = VirtualFrontEnd(bed, protocol, profile=profile, seed=2)
    frame = front.acquire()
    ideal = front.chain.ideal(bed.transfer_ohm(0.0), protocol)
    accuracy = profile.accuracy
    assert len(protocol) == 14786 and np.isfinite(frame.volts).all() and frame.conditions == ()
    assert np.all(np.abs(frame.volts - ideal) <= accuracy.relative * np.abs(ideal) + accuracy.absolute_v)
    with pytest.raises(ProtocolInvalid, match="only horizontally adjacent"):
        VirtualFrontEnd(bed, protocol_for(layout, "local", reach=2), profile=profile)


def test_a_bed_is_read_by_its_parallel_board_adaptively_and_holds_what_it_skips():
    from appliance.core.pixels import pixel_grid
    from appliance.core.pressure_map import loaded_electrodes
    from appliance.drivers.scan import Flag

    layout = get_layout("grid-16x32")
    protocol = default_protocol(layout)
    bed = VirtualBed(layout, empty_mat(layout), density=0.25, mechanics_merge=5)
    front = VirtualFrontEnd(bed, protocol, seed=3)
    assert front.chain.profile.name == "parallel" and front.adaptive
    empty = front.acquire()                                         # the first frame: a full pass
    heel = get_layout("grid-16x32").centroids_mm()[8 * 32 + 28]     # electrode 285, near the foot end
    place = placer(bed)
    place(Load(float(heel[0]), float(heel[1]), 60.0, 8.0))
    grid = pixel_grid(layout)
    kpa = np.zeros(grid.shape)
    kpa[grid.pixel_of(heel[None])[0] // grid.cols, grid.pixel_of(heel[None])[0] % grid.cols] = 8.0
    loaded = loaded_electrodes(kpa, grid, layout.centroids_mm())
    assert 285 in loaded and len(loaded) < 12
    frame = front.acquire(loaded)
    held = (frame.flags & Flag.HELD) > 0
    taken = np.isin(protocol.drive_index, front.plan.drives_for(loaded))
    assert np.array_equal(held, ~taken) and 0.25 < held.mean() < 0.5, "the fine drives far from the heel"
    assert np.array_equal(frame.volts[held], empty.volts[held]), "held: the last frame's readings"
    near_heel = np.isin(protocol.readings, [285]).any(axis=1)
    assert not held[near_heel].any() and np.abs(frame.volts - empty.volts)[near_heel].max() > 0
    assert np.all((front.acquire().flags & Flag.HELD) == 0), "no electrodes named: a full pass"
