"""KTC2023 segmentation score: perfect and empty predictions, label versions, shifts, bad input."""

from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest
import scipy.io as sio

from appliance.core.ktc_score import class_index, challenge_score
from appliance.errors import ModelInputInvalid

KTC = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "ktc2023"
TARGETS = (1, 2, 3, 4)

needs_data = pytest.mark.skipif(not (KTC / "GroundTruths").is_dir(),
                                reason=f"KTC2023 ground truths not found under {KTC}")


def load_truth(n: int, version: str = "GroundTruths") -> np.ndarray:
    return sio.loadmat(KTC / version / f"true{n}.mat")["truth"]


def disc(centre_row: float, centre_col: float, radius: float, label: int) -> np.ndarray:
    rows, cols = np.mgrid[:256, :256]
    image = np.zeros((256, 256), dtype=np.uint8)
    image[(rows - centre_row) ** 2 + (cols - centre_col) ** 2 < radius ** 2] = label
    return image


@needs_data
@pytest.mark.parametrize("n", TARGETS)
def test_perfect_reconstruction_scores_one(n):
    truth = load_truth(n)
    assert challenge_score(truth, truth.copy()) == pytest.approx(1.0, abs=1e-12)


@needs_data
@pytest.mark.parametrize("n, present, absent", [(3, 2, 1), (4, 1, 2)])
def test_all_water_on_a_one_class_target(n, present, absent):
    truth = load_truth(n)
    assert not np.any(truth == absent) and np.any(truth == present)
    water = np.zeros_like(truth)
    assert class_index(truth == absent, water == absent) == 1.0
    present_index = class_index(truth == present, water == present)
    assert present_index < 0.9
    score = challenge_score(truth, water)
    assert score == pytest.approx(0.5 * (1.0 + present_index), abs=1e-15)
    assert 0.5 <= score < 1.0


@needs_data
def test_all_water_on_two_class_targets_is_below_one_class_floor():
    for n in (1, 2):
        truth = load_truth(n)
        score = challenge_score(truth, np.zeros_like(truth))
        assert 0.0 < score < 0.5


@needs_data
def test_2024_truths_against_2023_08_versions():
    """SOURCE.md: the two label versions score 0.88-0.96 against each other."""
    if not (KTC / "GroundTruths_2023-08").is_dir():
        pytest.skip(f"{KTC / 'GroundTruths_2023-08'} not found")
    scores = {n: challenge_score(load_truth(n), load_truth(n, "GroundTruths_2023-08")) for n in TARGETS}
    print("2024 vs 2023-08 truths:", ", ".join(f"true{n}: {s:.4f}" for n, s in scores.items()))
    for n, s in scores.items():
        assert 0.88 <= s <= 0.96, f"true{n}: {s}"


def test_wrong_shape_scores_zero():
    truth = disc(128, 128, 40, 2)
    assert challenge_score(truth, truth[:255]) == 0.0
    assert challenge_score(truth, truth[:, :, None]) == 0.0
    assert challenge_score(truth, truth.T[:128]) == 0.0
    assert challenge_score(truth, np.zeros(256 * 256)) == 0.0


def test_bad_input_is_refused():
    truth = disc(128, 128, 40, 2)
    with pytest.raises(ModelInputInvalid, match=r"truth must be 256x256, got shape \(128, 128\)"):
        challenge_score(truth[:128, :128], truth[:128, :128])
    bad = truth.copy()
    bad[0, 0] = 3
    with pytest.raises(ModelInputInvalid, match=r"truth has labels other than 0.*1 pixel\(s\): 3"):
        challenge_score(bad, truth)
    recon = truth.astype(float)
    recon[5, 5:8] = [-1.0, 0.5, np.nan]
    with pytest.raises(ModelInputInvalid, match=r"reconstruction has labels other than 0.*3 pixel\(s\)"):
        challenge_score(truth, recon)
    with pytest.raises(ModelInputInvalid, match="differ in shape"):
        class_index(np.zeros((4, 4)), np.zeros((4, 5)))
    with pytest.raises(ModelInputInvalid, match="0/1 mask"):
        class_index(np.full((4, 4), 2), np.zeros((4, 4)))
    with pytest.raises(ModelInputInvalid, match="2-D"):
        class_index(np.zeros(16), np.zeros(16))


@pytest.mark.parametrize("label", [1, 2])
def test_shifting_an_object_lowers_the_score(label):
    truth = disc(128, 100, 25, label)
    scores = [challenge_score(truth, disc(128, 100 + shift, 25, label)) for shift in (0, 10, 30, 60)]
    assert scores[0] == pytest.approx(1.0, abs=1e-12)
    assert all(a > b + 1e-3 for a, b in pairwise(scores)), scores
    assert scores[-1] < 0.55  # 60 px off (more than a diameter) is no better than predicting nothing


def test_class_index_is_symmetric(rng):
    a = rng.random((256, 256)) < 0.1
    b = np.roll(a, 7, axis=1) | (rng.random((256, 256)) < 0.02)
    forward, backward = class_index(a, b), class_index(b, a)
    assert forward == pytest.approx(backward, abs=1e-14)
    assert 0.0 < forward < 1.0
    assert class_index(a, a) == pytest.approx(1.0, abs=1e-12)


def test_partial_overlap_lies_between_empty_and_perfect():
    empty = np.zeros((256, 256), dtype=bool)
    assert class_index(empty, empty) == 1.0
    target = disc(128, 128, 30, 1) == 1
    nothing = class_index(target, empty)
    half = class_index(target, disc(128, 128, 15, 1) == 1)
    assert abs(nothing) < 0.01
    assert nothing + 0.1 < half < 0.9
