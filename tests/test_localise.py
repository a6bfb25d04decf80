"""Region fitting: sub-pixel positions with honest uncertainties, several regions at once."""

import numpy as np
import pytest

from appliance.core.forward import simulate
from appliance.core.localise import find_regions
from appliance.core.named_layouts import get_layout
from appliance.core.phantoms import Inclusion, conductivity
from appliance.core.protocols import default_protocol

from conftest import grid_truth_and_model

LAYOUT = get_layout("grid-4x4")
PROTOCOL = default_protocol(LAYOUT)


@pytest.fixture(scope="module")
def setting():
    return grid_truth_and_model(1e-2)


def frame(setting, loads, rng, noise=1e-2):
    truth, reference, _ = setting
    v = simulate(truth, conductivity(truth, [Inclusion("rect", x, y, 20, 20, 0.6) for x, y in loads]), PROTOCOL)
    return v + rng.normal(0, noise * np.sqrt(np.mean(reference**2)), v.shape)


def test_fitted_positions_beat_image_centroids_at_one_percent_noise(setting):
    truth, reference, model = setting
    rng = np.random.default_rng(21)
    fitted, scaled = [], []
    for _ in range(16):
        x, y = rng.uniform(15, 85, 2)
        v = frame(setting, [(x, y)], rng)
        (region,) = model.regions(v, reference)[:1]
        error = np.hypot(region.x_mm - x, region.y_mm - y)
        fitted.append(error)
        scaled.append(error / np.hypot(region.sd_x_mm, region.sd_y_mm))
        assert -0.8 < region.change < -0.2 and 7 < region.radius_mm < 16
    print(f"fitted centre error median {np.median(fitted):.2f} mm; "
          f"error over predicted sd median {np.median(scaled):.2f}")
    assert np.median(fitted) < 0.6
    assert 0.3 < np.median(scaled) < 3.0, "the reported uncertainty is of the right size"


def test_two_loads_give_two_fitted_regions(setting):
    _, reference, model = setting
    rng = np.random.default_rng(22)
    regions = model.regions(frame(setting, [(30, 40), (70, 60)], rng, 1e-3), reference)
    assert len(regions) == 2
    found = sorted((round(r.x_mm), round(r.y_mm)) for r in regions)
    assert np.allclose(found, [(30, 40), (70, 60)], atol=2)


def test_no_change_no_region(setting):
    _, reference, model = setting
    assert model.regions(reference.copy(), reference) == []
    assert find_regions(np.zeros((4, 4))) == []
