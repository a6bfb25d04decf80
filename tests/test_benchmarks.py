"""The benchmark scripts stay runnable: each one's pieces run on a small case and report sane numbers."""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"


def load(name):
    sys.path.insert(0, str(BENCHMARKS))
    try:
        spec = importlib.util.spec_from_file_location(f"bench_{name}", BENCHMARKS / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    finally:
        sys.path.remove(str(BENCHMARKS))


def test_forward_benchmark_phases():
    forward = load("forward")
    from appliance.core.layouts import get_layout

    nodes, build, assemble, factor, solve, total = forward.phase_times(get_layout("grid-4x4"), 0.5)
    assert 300 < nodes < 1500
    assert 0 < assemble < factor and 0 < solve and total < 1.0


@pytest.fixture(scope="module")
def chapter5():
    return load("thesis_chapter5")


def test_chapter5_sweep_and_literal_check_on_phantom_c(chapter5, monkeypatch):
    monkeypatch.setattr(chapter5, "CONTRASTS", np.array([1e-3, 1e3]))
    phantom = chapter5.Phantom("C", "network")
    q, dvv, q_subset, dvv_trimmed = chapter5.sweep(phantom)
    assert q.shape == (7, 2) and np.all(q[:, 0] > 0) and np.all(q[:, 1] < 0)
    assert np.abs(q - q_subset).max() < 1e-9
    assert phantom.nominal_area(10) == pytest.approx(100 / 256)
    dq, ddvv = chapter5.literal_check(phantom, contrasts=(1e-3,))
    assert dq < 1e-4


def test_chapter5_sensitivity_map_peaks_at_the_centre_for_c(chapter5):
    values = chapter5.sensitivity_map(chapter5.Phantom("C", "network"), n=5)
    assert values.shape == (5, 5) and values[2, 2] == np.nanmax(values)
