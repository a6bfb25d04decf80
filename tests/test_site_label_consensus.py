"""The consensus site labels stay what their README says: the two readers' agreed labels untouched, every
disagreement settled with a note naming both readers' labels, every spot of every map present."""

import json
import re
from pathlib import Path

import pytest

from appliance.alerts.anatomy import SITES

LABELS = Path(__file__).resolve().parent / "data" / "site_labels"
DOUBLY_READ = (1, 4, 6, 11)
SPOT_KEYS = ("spot", "along_mm", "across_mm", "peak_mmhg")


def _load(*parts):
    return json.loads(LABELS.joinpath(*parts).read_text())


def _reader(labels):
    match = re.match(r"reader ([A-Z]),", labels["labeller"])
    assert match, f"labeller {labels['labeller']!r} names no reader"
    return match.group(1)


def _shown(site):
    return "null" if site is None else site


@pytest.mark.parametrize("subject", DOUBLY_READ)
def test_consensus_keeps_agreed_labels_and_settles_the_rest(subject):
    first = _load(f"pmatdata-S{subject}.json")
    second = _load("second-reader", f"pmatdata-S{subject}.json")
    consensus = _load("consensus", f"pmatdata-S{subject}.json")
    r1, r2 = _reader(first), _reader(second)
    assert consensus["labeller"].startswith(
        f"consensus: agreed labels of readers {r1} and {r2}; disagreements settled by reader F")
    assert set(consensus) == set(first) | {"settled"}
    assert consensus["subject"] == subject
    assert [m["posture_file"] for m in consensus["maps"]] == list(range(1, 18))

    settled = 0
    for mc, m1, m2 in zip(consensus["maps"], first["maps"], second["maps"], strict=True):
        assert mc["posture"] == m1["posture"]
        for sc, s1, s2 in zip(mc["spots"], m1["spots"], m2["spots"], strict=True):
            where = f"S{subject} #{mc['posture_file']} spot {sc['spot']}"
            assert [sc[k] for k in SPOT_KEYS] == [s1[k] for k in SPOT_KEYS], where
            assert sc["site"] is None or sc["site"] in SITES, where
            if s1["site"] == s2["site"]:
                assert (sc["site"], sc["note"]) == (s1["site"], s1["note"]), where
            else:
                settled += 1
                prefix = f"SETTLED ({r1}: {_shown(s1['site'])}, {r2}: {_shown(s2['site'])}): "
                assert sc["note"].startswith(prefix) and len(sc["note"]) > len(prefix) + 20, where
    assert consensus["settled"] == settled
