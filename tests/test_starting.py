"""The monitor's start-up progress: lines and start-up snapshots in the live view until the first map."""

import json

import pytest

from appliance.service.config import config_from_mapping
from appliance.service.live import LiveChannel
from appliance.service.starting import PHASES, StartingReport


def test_a_first_start_publishes_rising_start_up_snapshots_before_the_first_map(small_mat_calibration, tmp_path,
                                                                                 monkeypatch):
    """An empty cache: the model is built, the calibration read and the reference taken, each step on the live
    channel before the first frame's snapshot replaces them."""
    from appliance.core.pressure import save_pressure_calibration
    from appliance.service.assemble import assemble

    published = []
    publish = LiveChannel.publish
    monkeypatch.setattr(LiveChannel, "publish", lambda self, snapshot: (published.append(snapshot),
                                                                        publish(self, snapshot))[-1])
    lines: list[str] = []
    scenario = tmp_path / "empty-small-mat.toml"
    scenario.write_text("[scene]\nwidth_mm = 100\nheight_mm = 100\npitch_mm = 10\nduration_s = 60\n")
    save_pressure_calibration(tmp_path / "pressure.json", small_mat_calibration[1])
    config = config_from_mapping({"virtual": {"speed": 0.0, "scenario": str(scenario)},
                                  "monitor": {"layout": "grid-4x4", "frame_interval_s": 0.05,
                                              "calibration": str(tmp_path / "pressure.json"),
                                              "data_dir": str(tmp_path / "data"),
                                              "cache_dir": str(tmp_path / "models")}})
    daemon = assemble(config, say=lines.append)
    try:
        assert daemon.run(1) == 1
    finally:
        daemon.close()
    first_frame = next(k for k, s in enumerate(published) if "sequence" in s)
    starting = [s["starting"] for s in published[:first_frame]]
    assert all("starting" in s for s in published[:first_frame]) and "starting" not in published[first_frame]
    shares = [s["share"] for s in starting]
    assert shares == sorted(shares) and shares[0] == 0.0 and shares[-1] == PHASES["reference"][1]
    phases = [s["phase"] for s in starting]
    assert phases.count(PHASES["model"][0]) == 5                # meshing ... done
    assert PHASES["calibration"][0] in phases and phases[-1] == PHASES["reference"][0]
    assert "building the reconstruction model: meshing (0%)" in lines
    assert "taking the pressure calibration (0%)" in lines


def test_start_up_steps_never_go_back_and_a_bad_step_is_refused():
    lines: list[str] = []
    report = StartingReport(None, lines.append)
    report("model", 0.5, "solving")
    assert report.share == pytest.approx(0.4)
    report("calibration", 0.0)
    report("model", 0.1)                                         # a late report of an earlier phase
    assert report.share == pytest.approx(0.8)
    assert lines[0] == "building the reconstruction model: solving (50%)"
    with pytest.raises(ValueError, match="unknown start-up phase 'warming'"):
        report("warming", 0.5)
    with pytest.raises(ValueError, match="from 0 to 1, got 1.5"):
        report("model", 1.5)


def test_a_start_up_that_fails_says_so_on_the_live_channel_at_once(tmp_path, model_cache):
    """A scenario file that cannot be read stops the start-up: the live view then holds the step it stopped at,
    marked failed, rather than a start-up that seems still under way."""
    from appliance.errors import ApplianceError
    from appliance.service.assemble import assemble

    scenario = tmp_path / "damaged.toml"
    scenario.write_text("[scene\nwidth_mm = 100\n")
    config = config_from_mapping({"virtual": {"speed": 0.0, "scenario": str(scenario)},
                                  "monitor": {"layout": "grid-4x4", "data_dir": str(tmp_path / "data"),
                                              "cache_dir": str(model_cache)}})
    with pytest.raises(ApplianceError, match="damaged.toml"):
        assemble(config, say=lambda line: None)
    starting = json.loads((tmp_path / "data" / "live.json").read_text())["starting"]
    assert starting["failed"] is True and starting["phase"] in [words for words, _, _ in PHASES.values()]
