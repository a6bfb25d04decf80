"""The body frame's midline: the middle of the contact's width at each place along the body."""

from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import binary_opening

from appliance.alerts.anatomy import BodyView
from appliance.alerts.body_frame import MIDLINE_BAND, _midline, body_contact, fit_body_frame
from appliance.sim.body import MatGrid
from appliance.sim.recordings import pmat_scene, resample_onto

PMAT = Path(__file__).resolve().parents[2] / "shared" / "data" / "pmatdata"
CELLS = MatGrid(900.0, 1900.0, 1900.0 / 64)
PITCH = (1900.0 / 64, 900.0 / 30)


def midline_by_definition(view: BodyView, frame, s: np.ndarray) -> np.ndarray:
    """Every contact cell against every place: the slow, plain reading of the definition."""
    contact = binary_opening(body_contact(np.asarray(view.kpa, float)), np.ones((2, 2), dtype=bool))
    rows, cols = np.nonzero(contact)
    cs, cu = frame.body_fractions((rows + 0.5) * view.pitch_mm[0], (cols + 0.5) * view.pitch_mm[1])
    out = np.zeros(len(s))
    for i, place in enumerate(s):
        near = np.abs(cs - place) <= MIDLINE_BAND
        if near.any():
            out[i] = 0.5 * (cu[near].min() + cu[near].max())
    return out


@pytest.mark.skipif(not PMAT.is_dir(), reason="PmatData is not on this machine")
@pytest.mark.parametrize("subject,posture_file", [(1, 1), (2, 9), (5, 17), (8, 12)])
def test_the_midline_is_the_middle_of_the_contact_at_each_place_on_real_bodies(subject, posture_file):
    scene = pmat_scene(PMAT, subject, posture_file, MatGrid(900.0, 1900.0, 10.0))
    view = BodyView(resample_onto(scene.frames[len(scene.frames) // 2], 10.0, CELLS), PITCH, True)
    frame = fit_body_frame(view)
    s = np.concatenate([np.linspace(-0.2, 1.2, 301), [0.0, 0.5, 1.0]])   # off the body at both ends too
    expected = midline_by_definition(view, frame, s)
    assert np.count_nonzero(expected) > 150 and (expected[s < -0.1] == 0).all()
    assert np.allclose(_midline(view, frame, s), expected, rtol=0, atol=1e-12)


def test_the_midline_of_an_empty_map_is_zero():
    view = BodyView(np.zeros((64, 30)), PITCH, True)
    frame = fit_body_frame(BodyView(np.pad(np.full((40, 10), 5.0), ((10, 14), (10, 10))), PITCH, True))
    assert (_midline(view, frame, np.linspace(0, 1, 11)) == 0).all()
