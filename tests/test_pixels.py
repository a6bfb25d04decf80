"""The pixel grid and its map from forward elements."""

import math

import numpy as np
import pytest

from appliance.core.named_layouts import get_layout
from appliance.core.pixels import element_pixel_map, pixel_areas_mm2, pixel_grid
from appliance.errors import ConfigError

from conftest import PERIPHERAL_AND_GRID


def test_default_grids():
    assert pixel_grid(get_layout("grid-4x4")).shape == (16, 16)
    bed = pixel_grid(get_layout("grid-16x32"))
    assert (bed.rows, bed.cols) == (30, 64) and max(bed.pixel_mm) <= 30.0, "no bed pixel over 30 mm"
    disc = pixel_grid(get_layout("circular-16"))
    assert disc.n_inside < 256 and not disc.inside[0, 0] and disc.inside[8, 8]


@pytest.mark.parametrize("kind", ["fem", "network"])
@pytest.mark.parametrize("name", PERIPHERAL_AND_GRID)
def test_every_element_maps_wholly_onto_imaged_pixels(models, name, kind):
    model = models[name, kind]
    grid = pixel_grid(get_layout(name))
    mapping = element_pixel_map(model, grid)
    assert mapping.shape == (model.n_elements, grid.n_inside)
    assert np.allclose(np.asarray(mapping.sum(axis=1)).ravel(), 1.0)
    assert pixel_areas_mm2(model, mapping).sum() == pytest.approx(model.areas_mm2.sum(), rel=1e-12)


def test_pixel_areas_match_their_share_of_the_sheet(models):
    mapping = element_pixel_map(models["grid-4x4", "fem"], pixel_grid(get_layout("grid-4x4")))
    areas = pixel_areas_mm2(models["grid-4x4", "fem"], mapping)
    assert np.allclose(areas, 6.25**2, rtol=0.1)


def test_image_puts_nan_off_the_sheet():
    grid = pixel_grid(get_layout("circular-16"))
    image = grid.image(np.arange(grid.n_inside, dtype=float))
    assert image.shape == (16, 16)
    assert np.isnan(image[0, 0]) and image[8, 8] >= 0
    assert np.count_nonzero(~np.isnan(image)) == grid.n_inside
    assert grid.n_inside * (100 / 16) ** 2 == pytest.approx(math.pi * 50**2, rel=0.08)


def test_bad_grid_is_refused():
    with pytest.raises(ConfigError, match="at least one row"):
        pixel_grid(get_layout("grid-4x4"), 0, 4)
