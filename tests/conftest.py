"""Shared fixtures: a clean environment, the built-in layouts and their models, a ward's broker, station and beds,
and a throw-away PostgreSQL with the hospital history's tables."""

import functools
import os
import sys
from pathlib import Path

import numpy as np
import pytest

import appliance  # noqa: F401  (first: it pins BLAS to one thread before numpy loads)
from appliance.core.fem import build_fem_model
from appliance.core.named_layouts import get_layout
from appliance.core.network import build_network_model, network_for_layout

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

PERIPHERAL_AND_GRID = ("circular-16", "square-16", "grid-4x4")
BACKGROUND = "background"
"""Marks a test whose subject runs beside the whole suite (``background_soak``): its run starts once the tests are
collected and the test itself comes last."""


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config, items):
    items.sort(key=lambda item: item.get_closest_marker(BACKGROUND) is not None)      # stable: the rest keep order


def pytest_collection_finish(session):
    if not session.config.option.collectonly and any(item.get_closest_marker(BACKGROUND) for item in session.items):
        from background_soak import BackgroundSoak

        session.config.stash[SOAK] = BackgroundSoak()


def pytest_sessionfinish(session):
    soak = session.config.stash.get(SOAK, None)
    if soak is not None:
        soak.stop()


SOAK = pytest.StashKey()


@pytest.fixture(scope="session")
def background_soak(request):
    """The full-size hospital soak started when the suite began (only when a test marked ``background`` asks)."""
    soak = request.config.stash.get(SOAK, None)
    if soak is None:
        pytest.fail("the background soak starts only for a test marked background")
    return soak


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
def ca_certificate() -> Path:
    """A CA certificate TLS can load, for configurations that name one (its key was thrown away: nothing is signed
    by it)."""
    return Path(__file__).resolve().parent / "data" / "throwaway-ca.crt"


@pytest.fixture
def rng():
    return np.random.default_rng(20001)


@functools.lru_cache(maxsize=4)
def grid_truth_and_model(noise: float, truth_density: float = 3.0):
    """grid-4x4 simulated on a finer mesh (the truth and its homogeneous readings), and the
    appliance's reconstruction model of it with ``noise`` (share of the rms reading) declared."""
    from appliance.core.forward import simulate
    from appliance.core.model_cache import ModelSetup, build_model
    from appliance.core.protocols import default_protocol
    from appliance.core.reconstruct import ReconstructionOptions
    from appliance.core.regularisation import NoiseModel

    layout = get_layout("grid-4x4")
    protocol = default_protocol(layout)
    truth = build_fem_model(layout, density=truth_density)
    reference = simulate(truth, np.ones(truth.n_elements), protocol)
    model = build_model(ModelSetup(layout, protocol, ReconstructionOptions(noise=NoiseModel(0.0, noise))))
    return truth, reference, model


@functools.lru_cache(maxsize=8)
def sensor_of(layout_name: str, inclusions: tuple = ()):
    """The emulated mat of a layout (a forward solve), built once per layout and inclusions."""
    from appliance.drivers.emulated.sensor import ForwardSensor

    return ForwardSensor.of_layout(get_layout(layout_name), inclusions=list(inclusions))


def sensor_readings(sensor, protocol, current_a: float) -> np.ndarray:
    """What an ideal front end reads: V(meas+) - V(meas-) at ``current_a`` from the sensor's transfer matrix."""
    z = sensor.transfer
    a, b, c, d = (protocol.readings - 1).T
    return current_a * (z[c, a] - z[c, b] - z[d, a] + z[d, b])


@pytest.fixture
def emulated():
    """Factory: (board, front end) for a profile and layout on the emulated board; closed afterwards."""
    from appliance.drivers.backend import emulated_board, open_front_end
    from appliance.drivers.profile import board_profile

    opened = []

    def make(profile="reference", layout="grid-4x4", inclusions=(), seed=0, overrides=None):
        table = {"profile": profile, **(overrides or {})}
        board = emulated_board(board_profile(table), sensor_of(layout, tuple(inclusions)), seed=seed)
        front_end = open_front_end(board, board.profile)
        opened.append(board)
        return board, front_end

    yield make
    for board in opened:
        board.close()


@pytest.fixture(scope="session")
def model_cache(tmp_path_factory):
    """One model cache for the session's tests, so each bed-size model is built once."""
    return tmp_path_factory.mktemp("model-cache")


@pytest.fixture(scope="session")
def bed_monitoring(model_cache):
    """The default bed's reconstruction model and its virtual mat's calibration, as ``appliance run`` makes
    them: (model, calibration)."""
    from appliance.core.model_cache import cached_model, default_setup
    from appliance.service.assemble import virtual_calibration_path
    from appliance.service.config_sections import MonitorConfig
    from appliance.service.virtual_bed import VirtualBedSource
    from appliance.sim.scenes import load_scene

    layout = get_layout(MonitorConfig().layout)
    model, _ = cached_model(default_setup(layout), model_cache)
    source = VirtualBedSource(layout, load_scene("supine-still"), model.setup.protocol)
    calibration, _ = source.calibration(model, virtual_calibration_path(model_cache, model))   # where `run` finds it
    return model, calibration


@pytest.fixture(scope="session")
def small_mat_calibration(model_cache):
    """grid-4x4's model and a pressure calibration of its virtual mat with a reduced load set: (model, calibration)."""
    from appliance.calibration import calibration_loads, pressure_calibration
    from appliance.core.model_cache import ModelSetup, cached_model
    from appliance.core.protocols import default_protocol
    from appliance.service.virtual_bed import VirtualBedSource
    from appliance.sim.loads import empty_mat

    layout = get_layout("grid-4x4")
    protocol = default_protocol(layout)
    model, _ = cached_model(ModelSetup(layout, protocol), model_cache)
    source = VirtualBedSource(layout, empty_mat(layout), protocol, seed=4)
    calibration = pressure_calibration(source.acquire, source.place, model,
                                       calibration_loads(layout, pressures_kpa=(2, 5, 10, 20)))
    return model, calibration


@pytest.fixture
def broker():
    """A real Mosquitto on a free local port, stopped after the test."""
    from mqtt_broker import Broker

    b = Broker()
    b.start()
    yield b
    if b.process is not None:
        b.stop()


@pytest.fixture
def station(broker):
    """A ward station subscribed to ``broker``."""
    from mqtt_broker import subscribed_station

    with subscribed_station(broker.port, client_id="test-station", keepalive_s=5) as s:
        yield s


@pytest.fixture
def beds(broker, tmp_path):
    """Factory: a bed's ward link publishing as ``bed_id`` (its outbox in ``tmp_path``), connected; closed after
    the test."""
    from mqtt_broker import wait_until

    from appliance.alerts.ward_mqtt import mqtt_ward_link
    from appliance.store.outbox import Outbox

    made = []

    def make(bed_id, **options):
        options = {"summary_interval_s": 0.1, "resend_after_s": 0.5, **options}
        made.append(mqtt_ward_link("127.0.0.1", broker.port, bed_id, Outbox(tmp_path / f"{bed_id}-outbox.db"),
                             client_id=f"{bed_id}-link", **options))
        assert wait_until(lambda: made[-1].status()["connected"])
        return made[-1]
    yield make
    for link in made:
        link.close(timeout_s=1.0)


@pytest.fixture(scope="module")
def postgres():
    """A throw-away PostgreSQL server (``postgres_server``) shared by a module's tests; skipped without one."""
    from postgres_server import running_postgres

    with running_postgres() as server:
        yield server


@pytest.fixture
def history_dsn(postgres, request):
    """The connection string of a new database for this test on ``postgres``, with the history's tables."""
    import psycopg

    from appliance.hospital.history.schema import create_schema

    name = request.node.name.lower().replace("[", "_").replace("]", "").replace("-", "_")[:60]
    postgres.psql(f"CREATE DATABASE {name}")
    with psycopg.connect(postgres.dsn(name)) as connection:
        create_schema(connection)
    return postgres.dsn(name)
