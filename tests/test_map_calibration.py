"""Calibration from people's pressure maps: the maps as loads, the fit, and the virtual mat's shipped calibration."""

from pathlib import Path

import numpy as np
import pytest

from appliance.calibration import HEAD_END, HEAD_END_MM, Load, MapLoad, pressure_calibration
from appliance.core.model_cache import cached_model, default_setup
from appliance.core.named_layouts import get_layout
from appliance.core.pixels import pixel_grid
from appliance.core.pressure import KPA_PER_MMHG, load_pressure_calibration, save_pressure_calibration
from appliance.errors import ConfigError, DataFileInvalid
from appliance.service.monitor import Monitor
from appliance.service.virtual_bed import VirtualBedSource
from appliance.sim.loads import empty_mat
from appliance.sim.recordings import pmat_map_loads

PMAT = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "pmatdata"
BED = get_layout("grid-8x16")


def test_a_map_load_lies_along_the_bed_with_its_force_kept():
    cells = np.zeros((190, 90))
    cells[20:23, 40:43] = 10.0                  # near the head end (row 0), in the middle across
    load = MapLoad(cells, 10.0, "a head")
    grid = pixel_grid(BED)
    pixels = load.pixel_pressure(grid)
    assert pixels.shape == grid.shape == (30, 64)
    w, h = grid.pixel_mm
    assert pixels.sum() * w * h == pytest.approx(cells.sum() * 100.0)
    row, col = np.unravel_index(np.argmax(pixels), pixels.shape)
    assert col * w < 300 and 360 < row * h < 480, "the head end lies at x = 0 on a bed drawn landscape"
    with pytest.raises(ConfigError, match="covers 1000 x 900 mm, the mat 1900 x 900 mm"):
        MapLoad(np.zeros((100, 90)), 10.0, "too short").pixel_pressure(grid)


def test_people_are_taken_from_the_middle_of_each_recording():
    loads = pmat_map_loads(PMAT, [1], postures=(1, 2), frames_per_posture=3)
    assert [load.name.split("#")[0] for load in loads] == ["S1/1"] * 3 + ["S1/2"] * 3
    frames = [int(load.name.split("#")[1]) for load in loads[:3]]
    assert frames == sorted(frames) and frames[0] > 0
    weight_n = 87 * 9.80665                                          # S1: 87 kg
    assert loads[0].pressure_kpa.sum() * 100 * 1e-3 == pytest.approx(weight_n)
    with pytest.raises(DataFileInvalid, match="frames per posture must be 1 or more"):
        pmat_map_loads(PMAT, [1], frames_per_posture=0)


@pytest.fixture(scope="module")
def bed(tmp_path_factory):
    """grid-8x16 as the appliance models it, and a virtual mat to calibrate."""
    model, _ = cached_model(default_setup(BED), tmp_path_factory.mktemp("models"))
    source = VirtualBedSource(BED, empty_mat(BED), model.setup.protocol)
    return model, source


def test_maps_calibrate_a_bed_and_read_a_person_left_out(bed, tmp_path):
    model, source = bed
    calibration = pressure_calibration(source.acquire, source.place, model,
                                       pmat_map_loads(PMAT, [1, 2], postures=(1, 4, 6, 15)))
    assert calibration.notes["kind"] == "maps" and calibration.flat_field is None
    curve = calibration.curve
    assert curve.change[0] == 0 and curve.pressure[0] == 0 and np.all(np.diff(curve.pressure) >= 0)
    (head,) = calibration.zones                         # the bed's head end reads by a curve of its own
    assert head.name == HEAD_END and head.mask.any() and not head.mask.all()
    centres = model.reconstructor.grid.centres_mm.reshape(*head.mask.shape, 2)
    along = centres[..., 1] if BED.sheet.size_mm[1] > BED.sheet.size_mm[0] else centres[..., 0]
    assert along[head.mask].max() < HEAD_END_MM <= along[~head.mask].min()
    save_pressure_calibration(tmp_path / "cal.json", calibration)
    again = load_pressure_calibration(tmp_path / "cal.json")
    assert again.curve.pressure.tolist() == curve.pressure.tolist() and again.zones[0].name == HEAD_END

    monitor = Monitor(source.acquire, model, calibration)
    monitor.take_reference(source.empty_reference())
    person = pmat_map_loads(PMAT, [4], postures=(1,))[0]             # S4, in no fit, supine
    source.place(person)
    read = monitor.next_map().pressure_kpa / KPA_PER_MMHG
    truth = person.pixel_pressure(model.reconstructor.grid) / KPA_PER_MMHG
    assert np.corrcoef(np.nan_to_num(read).ravel(), truth.ravel())[0, 1] > 0.6
    assert 0.3 * truth.sum() < np.nansum(read) < 3 * truth.sum()
    far = truth == 0
    assert np.nanmax(read[far]) < 32, "nothing read at 32 mmHg where nobody lies"


def test_weights_and_maps_are_not_mixed(bed):
    model, source = bed
    with pytest.raises(ConfigError, match="either weights or whole maps, not both"):
        pressure_calibration(source.acquire, source.place, model,
                             [Load(950.0, 450.0, 100.0, 5.0)] + pmat_map_loads(PMAT, [1], postures=(1,)))


def test_the_virtual_mat_takes_the_shipped_calibration_that_fits_it(bed, tmp_path, monkeypatch):
    import appliance.service.virtual_bed as virtual_bed

    model, source = bed
    made = source.stamped(pressure_calibration(source.acquire, source.place, model,
                                               pmat_map_loads(PMAT, [1], postures=(1,))), model)
    monkeypatch.setattr(virtual_bed, "shipped_calibration", lambda name: made if name == BED.name else None)
    calibration, fresh = source.calibration(model, tmp_path / "virtual.json")
    assert not fresh and calibration.notes["maps"] == ["S1/1#" + made.notes["maps"][0].split("#")[1]]
    assert load_pressure_calibration(tmp_path / "virtual.json").notes["setup"] == model.setup.image_key()
    assert source.calibration(model, tmp_path / "virtual.json")[1] is False

    stiffer = VirtualBedSource(BED, empty_mat(BED), model.setup.protocol,
                               params=source.bed.params.__class__(foundation_kpa_per_mm=20.0))
    assert not stiffer.fits(made, model), "another mat's calibration does not fit"


def test_a_newer_shipped_calibration_replaces_the_copy_an_earlier_version_left(bed, tmp_path, monkeypatch):
    import dataclasses

    import appliance.service.virtual_bed as virtual_bed

    model, source = bed
    shipped = source.stamped(pressure_calibration(source.acquire, source.place, model,
                                                  pmat_map_loads(PMAT, [1], postures=(1,))), model)
    earlier = dataclasses.replace(shipped, notes={**shipped.notes, "maps": ["an earlier package's"]})
    save_pressure_calibration(tmp_path / "virtual.json", earlier)      # the mat's key fits: only its maps differ
    monkeypatch.setattr(virtual_bed, "shipped_calibration", lambda name: shipped if name == BED.name else None)
    calibration, fresh = source.calibration(model, tmp_path / "virtual.json")
    assert not fresh and calibration.notes["maps"] == shipped.notes["maps"]
    assert load_pressure_calibration(tmp_path / "virtual.json").notes["maps"] == shipped.notes["maps"]
    monkeypatch.setattr(virtual_bed, "shipped_calibration", lambda name: None)    # none shipped: the mat's own
    assert source.calibration(model, tmp_path / "virtual.json")[0].notes["maps"] == shipped.notes["maps"]


def test_the_shipped_bed_calibration_was_made_on_the_default_bed_mat():
    """The package's calibration is keyed on what the virtual bed's readings follow from: a change to the bed
    mat's mechanics (or to how they are described) would leave it unused and the bed calibrated anew."""
    from appliance.core.protocols import default_protocol
    from appliance.service.virtual_bed import shipped_calibration

    layout = get_layout("grid-16x32")
    source = VirtualBedSource(layout, empty_mat(layout), default_protocol(layout))
    assert shipped_calibration(layout.name).notes["mat"] == source.mat_key()
