"""Real recordings as scenes: PmatData and PoPu loading, cleaning, units, force and orientation."""

from pathlib import Path

import numpy as np
import pytest

from appliance.errors import DataFileInvalid
from appliance.sim.body import G_M_S2, MatGrid
from appliance.sim.field import KPA_PER_MMHG
from appliance.sim.recordings import (
    PMAT_SENSEL_MM, POPU_SENSEL_MM, clean_pmat_frames, force_n, pmat_scene, popu_scene, read_pmat_frames, resample_onto,
)

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
needs_data = pytest.mark.skipif(not (DATA / "pmatdata").is_dir() or not (DATA / "popu").is_dir(),
                                reason=f"shared recordings not present at {DATA}")


@pytest.mark.parametrize("src_pitch, grid", [(28.5, MatGrid(1000.0, 2000.0, 10.0)),
                                             (31.75, MatGrid(900.0, 2100.0, 7.0)),
                                             (5.0, MatGrid(400.0, 400.0, 23.0))])
def test_resampling_conserves_force(src_pitch, grid, rng):
    maps = rng.random((3, 64, 27)) * 10.0
    out = resample_onto(maps, src_pitch, grid)
    kept = force_n(out, grid.pitch_mm) / force_n(maps, src_pitch)
    assert out.shape == (3, *grid.shape)
    assert np.all(np.abs(kept - 1) < 1e-9), kept


def test_resampling_keeps_orientation_and_centres():
    source = np.zeros((4, 2))
    source[0, 0] = 1.0                                   # head end, patient's right
    out = resample_onto(source, 50.0, MatGrid(300.0, 400.0, 10.0))
    rows, cols = np.nonzero(out)
    assert (rows.min(), rows.max(), cols.min(), cols.max()) == (10, 14, 10, 14)


def test_cleaning_repairs_spikes_saturation_and_bad_frames():
    frames = np.full((5, 64, 32), 50.0)
    frames[0] = 0.0                                      # empty first frame
    frames[1] = 3000.0                                   # garbage frame
    frames[2, 10, 10] = 900.0                            # isolated spike
    frames[3, 20, 5] = 4095.0                            # saturated cell
    frames[4, 30:33, 10:13] = 2000.0                     # a real, contiguous high-pressure cluster
    clean, report = clean_pmat_frames(frames)
    assert report == {"bad_frames": 2, "bad_cells": 2}
    assert clean[2, 10, 10] == 50.0 and clean[3, 20, 5] == 50.0 and clean[4, 31, 11] == 2000.0
    assert np.array_equal(clean[0], clean[2]) and np.array_equal(clean[1], clean[0])


def test_missing_directory_and_bad_file_are_named(tmp_path):
    with pytest.raises(DataFileInvalid, match="PmatData data directory .*nowhere does not exist"):
        pmat_scene(tmp_path / "nowhere", 1, 1)
    with pytest.raises(DataFileInvalid, match="PoPu data directory .*nowhere does not exist"):
        popu_scene(tmp_path / "nowhere")
    bad = tmp_path / "1.txt"
    bad.write_text("0\t" * 2048 + "\n" + "0\t" * 2000 + "\n", encoding="ascii")
    with pytest.raises(DataFileInvalid, match=r"1.txt, line 2: 2000 values, expected 2048"):
        read_pmat_frames(bad)


@needs_data
@pytest.mark.parametrize("subject, posture, weight_kg", [(1, 1, 87.0), (3, 16, 100.0), (8, 6, 63.0)])
def test_pmat_scene_carries_the_subjects_weight(subject, posture, weight_kg):
    scene = pmat_scene(DATA / "pmatdata", subject, posture)
    assert scene.frames.shape[1:] == MatGrid().shape and scene.frames.min() >= 0
    forces = force_n(scene.frames, scene.grid.pitch_mm)
    assert np.all(np.abs(forces / (weight_kg * G_M_S2) - 1) < 1e-9), forces[:3]
    assert scene.info["share_off_mat"] < 0.02, scene.info
    peak_mmhg = np.median(scene.frames.max(axis=(1, 2))) / KPA_PER_MMHG
    assert 20 < peak_mmhg < 400, f"median frame peak {peak_mmhg:.0f} mmHg at {PMAT_SENSEL_MM} mm sensels"


@needs_data
def test_pmat_keeps_head_at_the_top_and_steps_at_1_hz():
    scene = pmat_scene(DATA / "pmatdata", 1, 1, MatGrid(1000.0, 2000.0, 10.0))
    raw, _ = clean_pmat_frames(read_pmat_frames(DATA / "pmatdata/experiment-i/S1/1.txt"))
    rows = (np.arange(64) + 0.5) * PMAT_SENSEL_MM + (2000.0 - 64 * PMAT_SENSEL_MM) / 2
    y_src = (raw[10].sum(axis=1) * rows).sum() / raw[10].sum()
    frame = scene.pressure_at(10.5).pressure_kpa
    y_out = (frame.sum(axis=1) * (np.arange(200) + 0.5) * 10.0).sum() / frame.sum()
    assert abs(y_out - y_src) < 10.0 and y_src < 1000.0, (y_out, y_src)
    top = np.nonzero(frame.sum(axis=1) > 0.01 * frame.sum(axis=1).max())[0][0] * 10.0
    assert top < 250.0, f"occiput should be near the top, first loaded row at {top} mm"
    assert scene.duration_s == len(scene.frames) and scene.changes(10.0, 11.0) and not scene.changes(10.0, 10.9)


@needs_data
def test_popu_scene_as_measured_and_scaled():
    scene = popu_scene(DATA / "popu", "supine1", 0)
    assert scene.frames.shape == (10, *MatGrid().shape) and scene.frames.min() >= 0
    ratio = scene.info["force_ratio"]
    assert 1.5 < ratio < 3.0, (f"PoPu read as mmHg at {POPU_SENSEL_MM} mm sensels carries {ratio:.2f} x the "
                               f"volunteer's 96 kg ({scene.info['recorded_force_n']:.0f} N)")
    assert 0.4 < scene.duration_s / 10 < 0.7, "snapshots about 0.52 s apart"
    scaled = popu_scene(DATA / "popu", "left1", 2, scale_to_weight=True)
    forces = force_n(scaled.frames, scaled.grid.pitch_mm)
    assert np.all(np.abs(forces / (96.0 * G_M_S2) - 1) < 1e-9)
    top, bottom = scene.frames[0, :50].sum(), scene.frames[0, -50:].sum()
    assert top > 2 * bottom, f"head and shoulders at the top: {top:.0f} vs {bottom:.0f} kPa-cells at the foot"
    first = np.nonzero(scene.frames[0].sum(axis=1) > 0)[0][0] * 10.0
    assert first < 100.0, f"occiput should be near the top, first loaded row at {first} mm"
