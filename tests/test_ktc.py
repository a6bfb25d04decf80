"""The KTC2023 tank: layout, patterns, levels, and the challenge score on the training set."""

from pathlib import Path

import numpy as np
import pytest
import scipy.io

from appliance.cli import main
from appliance.core.ktc import ktc_layout, load_ktc, removed_electrodes
from appliance.core.ktc_score import challenge_score
from appliance.core.reconstruct import readings_using
from appliance.errors import DataFileInvalid

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "ktc2023"
pytestmark = pytest.mark.skipif(not DATA.exists(), reason="the KTC2023 data set is not beside the repository")


def test_layout_numbers_counter_clockwise_from_the_top():
    layout = ktc_layout()
    c = layout.centroids_mm()
    assert c[0][0] == pytest.approx(115) and c[0][1] < 5                      # electrode 1 at the top
    assert c[8][0] < 5 and c[8][1] == pytest.approx(115)                      # electrode 9 on the left
    assert np.degrees(layout.electrodes[0].width_deg * np.pi / 180) * 115 * np.pi / 180 == pytest.approx(11.29, 0.01)


def test_patterns_become_the_protocol():
    ref = load_ktc(DATA / "TrainingData" / "ref.mat")
    assert len(ref.protocol) == 2356 and len(ref.current_ma) == 76
    assert len(ref.protocol.drives) == 72, "7-9, 15-17, 23-25 and 31-1 are each driven twice"
    assert ref.protocol.readings[0].tolist() == [1, 3, 1, 2]
    assert ref.protocol.readings[-1].tolist() == [31, 25, 31, 32]
    assert np.all((1.41 <= ref.current_ma) & (ref.current_ma <= 1.52))


def test_levels_remove_exactly_the_readings_the_challenge_removes():
    """SOURCE.md: 0, 732, 952, 1156, 1344, 1726 and 1843 NaNs at levels 1 to 7."""
    protocol = load_ktc(DATA / "TrainingData" / "ref.mat").protocol
    counts = [int(readings_using(protocol, removed_electrodes(level)).sum()) if level > 1 else 0
              for level in range(1, 8)]
    assert counts == [0, 732, 952, 1156, 1344, 1726, 1843]


@pytest.mark.parametrize(("content", "message"), [(None, "does not exist"), (b"junk", "is not a MAT file")])
def test_bad_files_are_refused(tmp_path, content, message):
    path = tmp_path / "data.mat"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(DataFileInvalid, match=message):
        load_ktc(path)


def test_a_mat_file_without_the_arrays_is_refused(tmp_path):
    path = tmp_path / "other.mat"
    scipy.io.savemat(path, {"x": np.ones(3)})
    with pytest.raises(DataFileInvalid, match="has none of Inj, Injref"):
        load_ktc(path)


def test_training_set_scores_at_least_3_4_of_4(tmp_path, capsys):
    scores = []
    for k in range(1, 5):
        labels = tmp_path / f"labels{k}.csv"
        code = main(["reconstruct", "--layout", "ktc-32", "--reference", str(DATA / "TrainingData" / "ref.mat"),
                     "--frame", str(DATA / "TrainingData" / f"data{k}.mat"), "--out", str(tmp_path / f"img{k}.csv"),
                     "--segment", str(labels), "--cache-dir", str(tmp_path / "cache")])
        assert code == 0, capsys.readouterr().err
        segmentation = np.loadtxt(labels, delimiter=",").astype(int)
        truth = scipy.io.loadmat(DATA / "GroundTruths" / f"true{k}.mat")["truth"]
        scores.append(challenge_score(truth, segmentation))
    print("KTC2023 training scores", np.round(scores, 3), "total", round(sum(scores), 3))
    assert sum(scores) >= 3.4
