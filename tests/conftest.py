"""Shared fixtures: a clean environment, the built-in layouts and their models."""

import appliance  # noqa: F401  (first: it pins BLAS to one thread before numpy loads)

import os

import numpy as np
import pytest

from appliance.core.fem import build_fem_model
from appliance.core.layouts import get_layout
from appliance.core.network import build_network_model, network_for_layout

PERIPHERAL_AND_GRID = ("circular-16", "square-16", "grid-4x4")


@pytest.fixture(autouse=True)
def clean_environment(monkeypatch):
    """No APPLIANCE_* setting of the developer's shell leaks into a test."""
    for name in list(os.environ):
        if name.startswith("APPLIANCE_"):
            monkeypatch.delenv(name)


@pytest.fixture(scope="session")
def models():
    """FEM and network models of each built-in layout, built once: {(name, kind): model}."""
    out = {}
    for name in PERIPHERAL_AND_GRID:
        layout = get_layout(name)
        out[name, "fem"] = build_fem_model(layout)
        out[name, "network"] = build_network_model(network_for_layout(layout))
    return out


@pytest.fixture
def rng():
    return np.random.default_rng(20001)
