"""The virtual bed re-solves only when the scene or temperature changed, and its fast path agrees with the slow one."""

import numpy as np
import pytest

import appliance.sim.bed as bed_module
from appliance.core.fem import build_fem_model
from appliance.core.forward import solve_electrodes
from appliance.core.named_layouts import get_layout
from appliance.core.network import build_network_model, network_for_layout
from appliance.core.protocols import default_protocol
from appliance.errors import ModelInputInvalid
from appliance.sim.bed import VirtualBed
from appliance.sim.scenes import load_scene
from appliance.sim.transfer import TransferSolver

BED = get_layout("grid-8x16")
BED_PROTOCOL = default_protocol(BED)
COARSE = {"density": 0.25, "mechanics_merge": 5}        # the bed's pipeline at a test's speed
AGREEMENT = 1e-9
"""Relative RMS difference allowed between the two solvers' changes of the readings: both are exact
factorisations, so they differ by rounding (about 1e-12 measured, at density 0.25 and 1)."""


def readings(transfer, protocol=BED_PROTOCOL):
    a, b, c, d = (protocol.readings - 1).T
    return transfer[c, a] - transfer[c, b] - transfer[d, a] + transfer[d, b]


def relative_rms(error, reference):
    return float(np.sqrt(np.mean(error ** 2)) / np.sqrt(np.mean(reference ** 2)))


def test_block_solver_agrees_with_a_field_per_electrode_on_a_moving_patient():
    times = (299.0, 300.5, 301.0, 302.0)                 # still, then shifting 3 cm
    block, fields = (VirtualBed(BED, load_scene("restless"), solver=s, **COARSE) for s in ("block", "fields"))
    fast = [readings(block.transfer_ohm(t)) for t in times]
    slow = [readings(fields.transfer_ohm(t)) for t in times]
    assert block.solves == fields.solves == len(times)
    for t in range(1, len(times)):
        change = slow[t] - slow[0]
        assert np.abs(change).max() > 0
        assert relative_rms((fast[t] - fast[0]) - change, change) < AGREEMENT
    assert relative_rms(fast[-1] - slow[-1], slow[-1]) < AGREEMENT


def test_transfer_solver_matches_solve_electrodes_on_the_small_mat():
    model = build_fem_model(get_layout("grid-4x4"))
    sigma = np.random.default_rng(4).uniform(1e-3, 1e-1, model.n_elements)     # a 100-fold contrast
    z = TransferSolver(model).transfer(sigma)
    reference = solve_electrodes(model, sigma).transfer
    assert np.abs(z - reference).max() < 1e-10 * np.abs(reference).max()


def test_transfer_solver_refuses_electrodes_spread_over_several_unknowns():
    with pytest.raises(ModelInputInvalid, match="one unknown of its own"):
        TransferSolver(build_network_model(network_for_layout(get_layout("grid-4x4"))))


def test_a_still_patient_costs_one_solve():
    bed = VirtualBed(BED, load_scene("supine-still"), **COARSE)
    first = bed.transfer_ohm(600.0)
    later = [bed.transfer_ohm(600.0 + k) for k in range(1, 11)]
    assert (bed.solves, bed.reuses) == (1, 10)
    assert all(z is first for z in later)


def test_the_cache_gives_what_a_forced_re_solve_gives():
    bed = VirtualBed(BED, load_scene("supine-still"), **COARSE)
    cached = bed.transfer_ohm(600.0).copy()
    bed.set_scene(bed.scene)
    forced = bed.transfer_ohm(600.0)
    assert bed.solves == 2
    assert relative_rms(readings(forced) - readings(cached), readings(cached)) < AGREEMENT


def test_time_after_the_scene_ends_costs_no_solve():
    scene = load_scene("leaves-bed")
    bed = VirtualBed(BED, scene, **COARSE)
    end = bed.transfer_ohm(scene.duration_s)
    assert bed.transfer_ohm(scene.duration_s + 60.0) is end
    assert bed.transfer_ohm(scene.duration_s + 3600.0) is end
    assert (bed.solves, bed.reuses) == (1, 2)


def test_a_moving_patient_re_solves_and_a_temperature_change_forces_a_re_solve():
    warm_from_s = 605.0
    bed = VirtualBed(BED, load_scene("supine-still"), temperature_c=lambda t: 24.0 + 2.0 * (t >= warm_from_s),
                     **COARSE)
    cool = bed.transfer_ohm(600.0)
    assert bed.transfer_ohm(604.0) is cool
    warm = bed.transfer_ohm(warm_from_s)
    assert bed.solves == 2
    # 2 degrees warmer, the liquid conducts 1.12 / 1.08 times better; the contacts' impedance does not change.
    ratio = np.median(warm[cool != 0] / cool[cool != 0])
    assert ratio == pytest.approx(1.08 / 1.12, rel=0.01)
    moving = VirtualBed(BED, load_scene("restless"), **COARSE)
    moving.transfer_ohm(299.0)
    moving.transfer_ohm(301.0)
    assert (moving.solves, moving.reuses) == (2, 0)


def test_the_solver_switch_chooses_the_path(monkeypatch):
    calls = []
    monkeypatch.setattr(bed_module, "solve_electrodes", lambda *a: calls.append(a) or solve_electrodes(*a))
    scene = load_scene("supine-still")
    VirtualBed(BED, scene, solver="block", **COARSE).transfer_ohm(600.0)
    assert calls == []
    bed = VirtualBed(BED, scene, solver="fields", **COARSE)
    bed.transfer_ohm(600.0)
    assert len(calls) == 1
    assert bed.seconds["transfer"] > 0 and bed.seconds["mechanics"] > 0
    with pytest.raises(ModelInputInvalid, match="solver must be one of"):
        VirtualBed(BED, scene, solver="woodbury")
