"""Posture: the rules (out of bed, sitting on the edge), the shipped model on subjects it never saw, and its file."""

from pathlib import Path

import numpy as np
import pytest

from appliance.alerts.anatomy import POSTURES, BodyView, body_view, posture_group
from appliance.alerts.posture import PostureModel, default_posture_model, is_sitting_on_edge, posture_features
from appliance.alerts.posture_training import BED_PITCH_MM, augmented, bed_views, mirrored
from appliance.core.named_layouts import get_layout
from appliance.core.pixels import pixel_grid
from appliance.errors import DataFileInvalid, ModelInputInvalid
from appliance.sim.recordings import pmat_scene, popu_scene

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
needs_data = pytest.mark.skipif(not (DATA / "pmatdata").is_dir() or not (DATA / "popu").is_dir(),
                                reason=f"shared recordings not present at {DATA}")
HELD_OUT = (4, 6, 11)
FILES = {1: "supine", 2: "right-90", 3: "left-90", 4: "right-30", 6: "left-30"}


@pytest.fixture(scope="module")
def held_out_views():
    """The middle frame of some of S4's, S6's and S11's recordings as the bed sees them: {(subject, file): view}."""
    views = {}
    for subject in HELD_OUT:
        for number in FILES:
            scene = pmat_scene(DATA / "pmatdata", subject, number)
            views[subject, number] = bed_views(scene.frames[len(scene.frames) // 2][None], scene.grid.pitch_mm)[0]
    return views


def bed_view_of(along_mm, across_mm, kpa, sigma_mm):
    """A view on the bed's pixels holding Gaussian patches centred at (along, across) mm of peak ``kpa``."""
    rows, cols = 64, 30
    a = (np.arange(rows)[:, None] + 0.5) * BED_PITCH_MM
    c = (np.arange(cols)[None, :] + 0.5) * BED_PITCH_MM
    field = sum(k * np.exp(-((a - y) ** 2 + (c - x) ** 2) / (2 * s**2))
                for y, x, k, s in zip(along_mm, across_mm, kpa, sigma_mm))
    return BodyView(field, (BED_PITCH_MM, BED_PITCH_MM), True)


def sitting_view(along_mm=900.0, right_edge=True):
    """Sitting on a long edge, facing out: two ischial patches 150 mm in from the edge, 120 mm apart, and
    the backs of both thighs running from them out to the edge."""
    width = 30 * BED_PITCH_MM
    depth = [150.0, 150.0, 60.0, 60.0]
    across = [d if right_edge else width - d for d in depth]
    along = [along_mm - 60, along_mm + 60, along_mm - 90, along_mm + 90]
    return bed_view_of(along, across, [12.0, 12.0, 5.0, 5.0], [35.0, 35.0, 60.0, 60.0])


def test_empty_mat_and_a_bag_are_out_of_bed():
    model = default_posture_model()
    empty = BodyView(np.zeros((64, 30)), (BED_PITCH_MM, BED_PITCH_MM), True)
    bag = bed_view_of([900.0], [450.0], [8.0], [40.0])                   # a few kg on a small patch
    for view in (empty, bag):
        estimate = model.classify(view)
        assert (estimate.posture, estimate.confidence) == ("out-of-bed", 1.0)


@pytest.mark.parametrize("along_mm, right_edge", [(900.0, True), (900.0, False), (400.0, True), (1500.0, False)])
def test_synthetic_sitting_maps_are_sitting_on_the_edge(along_mm, right_edge):
    view = sitting_view(along_mm, right_edge)
    assert 250 < view.kpa.sum() * BED_PITCH_MM**2 * 1e-3 < 700            # about the upper body's weight (N)
    assert default_posture_model().classify(view).posture == "sitting-edge"


def test_sitting_in_the_middle_of_the_mat_is_not_sitting_on_the_edge():
    view = sitting_view()
    assert not is_sitting_on_edge(BodyView(np.roll(view.kpa, 10, axis=1), view.pitch_mm, True))


@needs_data
def test_held_out_subjects_lying_postures_are_named(held_out_views):
    model = default_posture_model()
    for (subject, number), view in held_out_views.items():
        estimate = model.classify(view)
        assert posture_group(estimate.posture) == posture_group(FILES[number]), (subject, number, estimate)
        assert not is_sitting_on_edge(view)
    fully_on_a_side = {key: model.classify(v).posture for key, v in held_out_views.items() if key[1] in (2, 3)}
    assert all(posture == FILES[key[1]] for key, posture in fully_on_a_side.items()), fully_on_a_side


@needs_data
def test_estimate_is_a_distribution_over_every_posture(held_out_views):
    estimate = default_posture_model().classify(held_out_views[4, 1])
    assert set(estimate.probabilities) == set(POSTURES)
    assert 0.0 <= estimate.confidence <= 1.0
    assert estimate.confidence == estimate.probabilities[estimate.posture]
    assert sum(estimate.probabilities.values()) == pytest.approx(1.0)


def test_the_likeliest_group_wins_over_the_likeliest_posture():
    """Left at 30 and at 60 degrees, 0.31 and 0.29, make a left side likelier than a back at 0.4: the estimate is the
    likelier of the left postures, and it is sure of its group only when the group's sum reaches the floor."""
    n_features = len(posture_features(sitting_view()))
    classes = ("supine", "left-30", "left-60", "right-30")
    for shares, posture, sure in (((0.4, 0.31, 0.29, 0.0), "left-30", False), ((0.1, 0.35, 0.55, 0.0), "left-60", True),
                                  ((0.5, 0.2, 0.2, 0.1), "supine", False)):
        bias = np.log(np.array(shares) + 1e-12)
        estimate = PostureModel(classes, np.zeros((4, n_features)), bias).classify(sitting_view(along_mm=900.0,
                                                                                             right_edge=True))
        assert estimate.posture == "sitting-edge"        # the rules come first
        view = bed_view_of([400.0, 900.0, 1500.0], [450.0, 450.0, 450.0], [6.0, 8.0, 4.0], [120.0, 150.0, 120.0])
        estimate = PostureModel(classes, np.zeros((4, n_features)), bias).classify(view)
        assert (estimate.posture, estimate.sure) == (posture, sure), shares
        assert estimate.confidence == pytest.approx(shares[classes.index(posture)])


@needs_data
def test_the_bed_pixel_map_position_and_weight_do_not_matter(held_out_views):
    """The 30 x 64 map of the bed, through body_view; moved 60 mm across and 90 mm along, and 30 % heavier."""
    grid = pixel_grid(get_layout("grid-16x32"))
    model = default_posture_model()
    for key in ((6, 1), (6, 2), (11, 3)):
        pixel_map = held_out_views[key].kpa.T
        moved = 1.3 * np.roll(np.roll(pixel_map, 2, axis=0), 3, axis=1)
        assert model.classify(body_view(moved, grid)).posture == model.classify(body_view(pixel_map, grid)).posture


@needs_data
def test_a_mirrored_map_swaps_the_side(held_out_views):
    model = default_posture_model()
    for number in (2, 3):
        view = held_out_views[11, number]
        mirror = BodyView(view.kpa[:, ::-1], view.pitch_mm, view.transposed)
        assert model.classify(mirror).posture == mirrored(model.classify(view).posture)


@needs_data
def test_prone_on_the_held_out_popu_variation():
    scene = popu_scene(DATA / "popu", "prone1", 2, scale_to_weight=True)
    views = bed_views(scene.frames[3:7], scene.grid.pitch_mm)
    assert all(default_posture_model().classify(v).posture == "prone" for v in views)


def test_bad_input_is_refused_clearly():
    model = default_posture_model()
    with pytest.raises(ModelInputInvalid, match="2-D pressure map"):
        model.classify(BodyView(np.ones(64), (BED_PITCH_MM, BED_PITCH_MM), True))
    with pytest.raises(ModelInputInvalid, match="no finite value"):
        model.classify(BodyView(np.full((64, 30), np.nan), (BED_PITCH_MM, BED_PITCH_MM), True))
    with pytest.raises(ValueError, match="shape"):
        body_view(np.zeros((64, 30)), pixel_grid(get_layout("grid-16x32")))


def test_save_and_load_give_identical_predictions(tmp_path):
    model = default_posture_model()
    path = tmp_path / "model.npz"
    model.save(path)
    again = PostureModel.load(path)
    features = np.array([posture_features(sitting_view(a)) for a in (300.0, 900.0)])
    assert again.classes == model.classes and again.info == model.info
    assert np.array_equal(again.probabilities(features), model.probabilities(features))
    (tmp_path / "bad.npz").write_bytes(b"not a model")
    with pytest.raises(DataFileInvalid, match="bad.npz"):
        PostureModel.load(tmp_path / "bad.npz")


def test_shipped_model_never_saw_the_validation_subjects():
    info = default_posture_model().info
    assert set(info["sources"]) == {"S1", "S2", "S3", "S5", "S7", "S8", "S9", "S10", "popu/v0", "popu/v1"}


def test_augmented_maps_read_light_load_as_none_like_the_reconstruction():
    """The same augmentation with a floor reads every cell under the floor it drew (up to 0.3 kPa) as zero and
    leaves the others as they were."""
    along, across = np.meshgrid(np.arange(200), np.arange(90), indexing="ij")
    field = 6.0 * np.exp(-((along - 100) ** 2 / 2000 + (across - 45) ** 2 / 300))[None]      # 10 mm cells, kPa
    floored = augmented(field, 10.0, np.random.default_rng(1), floor_kpa=0.3)[0].kpa
    kept = augmented(field, 10.0, np.random.default_rng(1), floor_kpa=0.0)[0].kpa
    level = floored[floored > 0].min()
    assert kept[kept > 0].min() < level < 0.3 and (floored == 0).sum() > (kept == 0).sum()
    assert np.array_equal(floored, np.where(kept >= level, kept, 0.0))
