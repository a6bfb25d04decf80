"""The engineering page and commands: roles, CSRF, argument checks, and each task run by the real small daemon."""

import dataclasses
import html
import io
import json

import numpy as np
import pytest
from werkzeug.datastructures import FileStorage
from werkzeug.test import encode_multipart

from appliance.core.frames import load_frame
from appliance.core.named_layouts import get_layout
from appliance.core.pressure import layout_fingerprint, load_pressure_calibration, save_pressure_calibration
from appliance.core.protocols import default_protocol
from appliance.service.engineering import engineering_commands
from appliance.service.engineering_tasks import checked_args
from appliance.service.virtual_bed import VirtualBedSource
from appliance.sim.loads import empty_mat
from appliance.store import Store
from webui import create_app
from webui_client import client_as, token

GRID = get_layout("grid-4x4")
PROTOCOL = default_protocol(GRID)


@pytest.fixture(scope="module")
def small_mat(model_cache):
    """grid-4x4's model and a quick calibration of its virtual mat (9 loads, seconds to make: enough to read the
    scene's load well above the alert threshold): (model, calibration)."""
    from appliance.calibration import calibration_loads, pressure_calibration
    from appliance.core.model_cache import ModelSetup, cached_model

    model, _ = cached_model(ModelSetup(GRID, PROTOCOL), model_cache)
    source = VirtualBedSource(GRID, empty_mat(GRID), PROTOCOL, seed=4)
    return model, pressure_calibration(source.acquire, source.place, model,
                                       calibration_loads(GRID, positions=1, pressures_kpa=(2, 10, 20)))


@pytest.fixture
def app(tmp_path):
    return create_app(tmp_path, secure_cookies=False, TESTING=True)


def queued(tmp_path) -> list:
    with Store.open(tmp_path / "appliance.db") as store:
        return store.pending_commands()


def audited(app) -> list:
    return [e["action"] for e in app.extensions["users"].audit_log() if e["action"].startswith("engineering")]


# Who may do what.

GET_ROUTES = ("/engineering", "/api/engineering/files", "/api/engineering/readings/readings-x.csv",
              "/engineering/files/readings-x.csv")
POST_ROUTES = ("/engineering/acquire", "/engineering/capture-reference", "/engineering/upload")


def test_an_anonymous_request_is_sent_to_log_in_or_refused(app):
    client_as(app, "admin")                                    # there is an account, so no first-start redirect
    anonymous = app.test_client()
    assert anonymous.get("/engineering").headers["Location"].startswith("/login")
    assert anonymous.get("/api/engineering/files").status_code == 401
    assert anonymous.post("/engineering/acquire", data={"averages": "1"}).status_code == 400   # no CSRF token


def test_a_nurse_gets_403_on_every_engineering_route(app, tmp_path):
    nurse = client_as(app, "nurse")
    csrf = token(nurse, "/")
    for path in GET_ROUTES:
        assert nurse.get(path).status_code == 403, path
    for path in POST_ROUTES:
        assert nurse.post(path, data={"averages": "1", "csrf_token": csrf}).status_code == 403, path
    assert queued(tmp_path) == [] and audited(app) == []


def test_the_nav_shows_engineering_to_an_engineer_only(app):
    assert 'href="/engineering"' in client_as(app, "engineer").get("/").get_data(as_text=True)
    assert 'href="/engineering"' not in client_as(app, "nurse").get("/").get_data(as_text=True)


def test_a_task_without_the_csrf_token_is_refused(app, tmp_path):
    engineer = client_as(app, "engineer")
    assert engineer.post("/engineering/acquire", data={"averages": "30"}).status_code == 400
    assert queued(tmp_path) == [] and audited(app) == []


# Arguments.

BAD_ARGUMENTS = [
    ("acquire", {"averages": "0"}, "averages must be an integer from 1 to 100, got '0'"),
    ("acquire", {"averages": "101"}, "averages must be an integer from 1 to 100, got '101'"),
    ("acquire", {"averages": "x"}, "averages must be an integer from 1 to 100, got 'x'"),
    ("acquire", {}, "averages is missing; it must be an integer from 1 to 100"),
    ("series", {"count": "1", "interval_s": "1"}, "count must be an integer from 2 to 600, got '1'"),
    ("series", {"count": "601", "interval_s": "1"}, "count must be an integer from 2 to 600, got '601'"),
    ("series", {"count": "10", "interval_s": "61"}, "interval_s must be a number from 0 to 60, got '61'"),
    ("save", {"what": "video"}, "what must be one of image, got 'video'"),
    ("calibrate", {"kind": "sensitivity"}, "kind must be one of pressure, got 'sensitivity'"),
    ("load", {"what": "calibration", "file": "../x"}, "file must be a plain file name in engineering/"),
    ("load", {"what": "calibration", "file": "/etc/passwd"}, "file must be a plain file name in engineering/"),
    ("load", {"what": "calibration", "file": ".."}, "file must be a plain file name in engineering/"),
]


def test_each_bad_argument_is_a_400_naming_it_and_nothing_is_queued_or_audited(app, tmp_path):
    engineer = client_as(app, "engineer")
    csrf = token(engineer, "/engineering")
    for task, fields, message in BAD_ARGUMENTS:
        answer = engineer.post(f"/engineering/{task}", data={**fields, "csrf_token": csrf})
        assert answer.status_code == 400 and message in html.unescape(answer.get_data(as_text=True)), (task, fields)
        as_json = engineer.post(f"/engineering/{task}", json=fields, headers={"X-CSRF-Token": csrf})
        assert as_json.status_code == 400 and message in as_json.get_json()["error"], (task, fields)
    assert queued(tmp_path) == [] and audited(app) == []


def test_an_unknown_task_is_not_found_and_extra_arguments_are_refused(app, tmp_path):
    engineer = client_as(app, "engineer")
    csrf = token(engineer, "/engineering")
    assert engineer.post("/engineering/format-disk", data={"csrf_token": csrf}).status_code == 404
    extra = engineer.post("/engineering/acquire", json={"averages": 1, "path": "/tmp"}, headers={"X-CSRF-Token": csrf})
    assert extra.status_code == 400 and extra.get_json()["error"] == "acquire takes averages, not path"
    assert queued(tmp_path) == []


def test_arguments_are_brought_to_their_types_with_defaults():
    assert checked_args("acquire", {"averages": "30"}) == {"averages": 30}
    assert checked_args("series", {"count": 3, "interval_s": "0.5"}) == {"count": 3, "interval_s": 0.5}
    assert checked_args("calibrate", {"kind": "pressure"}) == {"kind": "pressure", "positions": 2}
    with pytest.raises(ValueError, match="averages must be an integer"):
        checked_args("acquire", {"averages": True})


BAD_UPLOADS = [
    ("cal.json", b"{not json", "is not valid JSON"),
    ("cal.json", b'{"format": "something else"}', "is not a pressure calibration"),
    ("cal.txt", b"{}", "is neither .json (a pressure calibration) nor .toml"),
    ("monitor.toml", b'[monitor]\nsource = "serial"\n', "source must be one of virtual, emulated, hardware"),
    ("..cal.json", b"{}", "file must be a plain file name in engineering/"),
]


def test_an_upload_that_is_not_a_calibration_or_configuration_is_refused_and_not_saved(app, tmp_path):
    engineer = client_as(app, "engineer")
    csrf = token(engineer, "/engineering")
    for name, content, message in BAD_UPLOADS:
        answer = engineer.post("/engineering/upload", data={"file": (io.BytesIO(content), name), "csrf_token": csrf})
        assert answer.status_code == 400 and message in html.unescape(answer.get_data(as_text=True)), name
    boundary, body = encode_multipart({"file": FileStorage(io.BytesIO(b" " * (1024 * 1024 + 1)), "big.json"),
                                       "csrf_token": csrf})            # as bytes: the client's spooling leaks a file
    big = engineer.post("/engineering/upload", data=body, content_type=f"multipart/form-data; boundary={boundary}")
    assert big.status_code == 400 and "big.json is over the 1024 KiB an upload may be" in big.get_data(as_text=True)
    assert not (tmp_path / "engineering").exists() or not any((tmp_path / "engineering").iterdir())
    assert audited(app) == []


def test_an_uploaded_calibration_is_saved_listed_and_downloadable(app, tmp_path, small_mat):
    _, calibration = small_mat
    save_pressure_calibration(tmp_path / "made.json", calibration)
    content = (tmp_path / "made.json").read_bytes()
    engineer = client_as(app, "engineer")
    csrf = token(engineer, "/engineering")
    answer = engineer.post("/engineering/upload",
                           data={"file": (io.BytesIO(content), "bench.json"), "csrf_token": csrf})
    assert answer.status_code == 303
    assert (tmp_path / "engineering" / "bench.json").read_bytes() == content
    assert [f["name"] for f in engineer.get("/api/engineering/files").get_json()] == ["bench.json"]
    with engineer.get("/engineering/files/bench.json") as download:
        assert download.data == content and "attachment" in download.headers["Content-Disposition"]
    assert engineer.get("/engineering/files/other.json").status_code == 404
    again = engineer.post("/engineering/upload", data={"file": (io.BytesIO(content), "bench.json"), "csrf_token": csrf})
    assert again.status_code == 400 and "already in engineering/" in again.get_data(as_text=True)
    assert audited(app) == ["engineering upload"]


def implausible_variants(calibration) -> list[tuple[str, object, str]]:
    """(file name, a calibration a monitor must not read through, what the refusal names)."""
    from appliance.core.pressure import PressureCurve

    change, pressure = calibration.curve.change, calibration.curve.pressure
    swapped = pressure.copy()
    swapped[1] = pressure[2] + 1.0                                   # falls between the second and third knots
    return [("flat.json", dataclasses.replace(calibration, curve=PressureCurve(change, np.zeros_like(pressure))),
             "the curve is constant: it reads every change as 0 kPa"),
            ("falling.json", dataclasses.replace(calibration, curve=PressureCurve(change, swapped)),
             "the curve is not monotonic: it falls from"),
            ("scaled.json", dataclasses.replace(calibration, curve=PressureCurve(change, pressure * 0.02)),
             "reads a change of 1 (the liquid film's whole conductance) as"),
            ("stretched.json", dataclasses.replace(calibration, curve=PressureCurve(change * 20, pressure)),
             "a mat's curve reads 40 to 1500 mmHg there")]


def test_an_implausible_calibration_upload_is_refused_naming_what_is_wrong(app, tmp_path, small_mat):
    _, calibration = small_mat
    engineer = client_as(app, "engineer")
    csrf = token(engineer, "/engineering")
    for name, bad, message in implausible_variants(calibration):
        save_pressure_calibration(tmp_path / name, bad)
        answer = engineer.post("/engineering/upload",
                               data={"file": (io.BytesIO((tmp_path / name).read_bytes()), name), "csrf_token": csrf})
        assert answer.status_code == 400 and message in html.unescape(answer.get_data(as_text=True)), name
    assert not (tmp_path / "engineering").exists() or not any((tmp_path / "engineering").iterdir())
    assert audited(app) == []


def test_load_refuses_an_implausible_calibration_and_keeps_the_running_one(small_mat, tmp_path):
    daemon = daemon_for(small_mat, tmp_path)
    running = daemon.monitor.calibration
    (tmp_path / "engineering").mkdir()
    for name, bad, message in implausible_variants(running):
        save_pressure_calibration(tmp_path / "engineering" / name, bad)
        refused = run(daemon, tmp_path, "load", {"what": "calibration", "file": name})
        assert refused["state"] == "refused" and message in refused["result"], name
        assert daemon.monitor.calibration is running
    daemon.close()


def test_an_open_pressure_alarm_outlives_a_calibration_that_reads_less_until_the_site_is_relieved(small_mat,
                                                                                                 tmp_path):
    from appliance.core.pressure import PressureCurve
    from test_daemon import FlakySource, small_daemon

    daemon, events = small_daemon(small_mat, tmp_path, FlakySource(failing=()), alarm_dose=0.05,
                                  recovery="decay", relief_min=30)
    daemon.add_commands(engineering_commands(daemon, data_dir=tmp_path, cache_dir=tmp_path / "models"))
    while not daemon.pipeline.engine.alarms("clinical"):
        daemon.run(1)
    [alarm] = daemon.pipeline.engine.alarms("clinical")
    peak_mmhg = max(s.peak_kpa for s in daemon.pipeline.sites) / 0.133322
    running = daemon.monitor.calibration
    lower = dataclasses.replace(running, curve=PressureCurve(running.curve.change,
                                                             running.curve.pressure * 0.8 * 32 / peak_mmhg))
    (tmp_path / "engineering").mkdir()
    save_pressure_calibration(tmp_path / "engineering" / "lower.json", lower)
    result(run(daemon, tmp_path, "load", {"what": "calibration", "file": "lower.json"}))
    assert max(s.peak_kpa for s in daemon.pipeline.sites) / 0.133322 < 32          # the site reads relieved now
    assert daemon.pipeline.dose.doses()["mat"] < 0.05                     # and its dose has decayed below the alarm
    assert [a.alarm_id for a in daemon.pipeline.engine.alarms("clinical")] == [alarm.alarm_id]  # still open
    daemon.run(3)                                                   # relieved for the relief time: it ends as usual
    daemon.close()
    assert [e.alarm_id for e in events if e.kind == "ended"] == [alarm.alarm_id]


# The tasks, run by the monitor daemon.

def daemon_for(small_mat, tmp_path, source=None):
    """The small daemon of test_daemon with the engineering commands, writing under ``tmp_path``."""
    from test_daemon import FlakySource, small_daemon

    daemon, _ = small_daemon(small_mat, tmp_path, source or FlakySource(failing=()))
    daemon.add_commands(engineering_commands(daemon, data_dir=tmp_path, cache_dir=tmp_path / "models"))
    return daemon


def empty_source(frame_interval_s=60.0):
    return VirtualBedSource(GRID, empty_mat(GRID), PROTOCOL, frame_interval_s=frame_interval_s)


def run(daemon, tmp_path, kind, args=None):
    """Queue ``kind`` as the screen would, let the daemon take a frame, and return the command."""
    with Store.open(tmp_path / "appliance.db") as screen:
        command_id = screen.queue_command(kind, args or {}, "engineer.test")
    daemon.run(1)
    with Store.open(tmp_path / "appliance.db") as screen:
        return screen.command(command_id)


def result(command) -> dict:
    assert command["state"] == "done", command["result"]
    return json.loads(command["result"])


def recorded_progress(daemon) -> list:
    """Every share a command reports, as the store is told it."""
    shares, set_progress = [], daemon.store.set_progress

    def record(command_id, share, note=""):
        shares.append(share)
        set_progress(command_id, share, note)

    daemon.store.set_progress = record
    return shares


def test_an_averaged_acquisition_is_a_readings_file_with_less_noise_than_one_set(small_mat, tmp_path):
    daemon = daemon_for(small_mat, tmp_path, empty_source())
    shares = recorded_progress(daemon)
    first = result(run(daemon, tmp_path, "acquire", {"averages": 30}))
    second = result(run(daemon, tmp_path, "acquire", {"averages": 30}))
    single = result(run(daemon, tmp_path, "acquire", {"averages": 1}))
    daemon.close()
    assert shares[:30] == pytest.approx([k / 30 for k in range(1, 31)])
    assert (first["sets"], first["readings"], first["usable"], first["flagged_electrodes"]) == (30, 448, 448, [])
    frames = [load_frame(tmp_path / "engineering" / r["file"], 16) for r in (first, second, single)]
    assert all((f.protocol.readings == PROTOCOL.readings).all() for f in frames)
    a, b, one = (f.volts for f in frames)
    assert first["min_volts"] == pytest.approx(a.min()) and first["max_volts"] == pytest.approx(a.max())
    # two averages of 30 differ by sqrt(2/30) of the noise, a single set from an average by sqrt(31/30) of it
    assert 0.15 < np.std(a - b) / np.std(one - a) < 0.4


def test_a_series_writes_numbered_readings_files(small_mat, tmp_path):
    daemon = daemon_for(small_mat, tmp_path, empty_source())
    series = result(run(daemon, tmp_path, "series", {"count": 3, "interval_s": 0}))
    daemon.close()
    assert [name[-8:] for name in series["files"]] == ["-001.csv", "-002.csv", "-003.csv"]
    volts = [load_frame(tmp_path / "engineering" / name, 16).volts for name in series["files"]]
    assert (series["sets"], series["stopped_early"]) == (3, False)
    assert not np.array_equal(volts[0], volts[1])                       # three sets, not one written thrice


def test_the_readings_api_groups_a_saved_file_per_drive_pair(small_mat, tmp_path, app):
    daemon = daemon_for(small_mat, tmp_path)
    name = result(run(daemon, tmp_path, "acquire", {"averages": 2}))["file"]
    daemon.close()
    engineer = client_as(app, "engineer")
    data = engineer.get(f"/api/engineering/readings/{name}").get_json()
    drives = list(dict.fromkeys(map(tuple, PROTOCOL.readings[:, :2].tolist())))
    assert [tuple(g["drive"]) for g in data["groups"]] == drives
    for group in data["groups"]:
        rows = PROTOCOL.readings[(PROTOCOL.readings[:, :2] == group["drive"]).all(axis=1)]
        assert [r["measure"] for r in group["readings"]] == rows[:, 2:].tolist()
    saved = load_frame(tmp_path / "engineering" / name, 16).volts
    flat = [r["volts"] for g in data["groups"] for r in g["readings"]]
    assert np.allclose([np.nan if v is None else v for v in flat], saved, equal_nan=True)
    assert data["usable"] == int(np.isfinite(saved).sum()) < 448                 # the load saturates a few
    page = engineer.get("/engineering").get_data(as_text=True)
    assert name in page and f"/engineering/files/{name}" in page
    assert engineer.get("/api/engineering/readings/..").status_code == 400


def test_the_virtual_contact_check_and_self_test_find_a_disconnected_electrode(small_mat, tmp_path):
    daemon = daemon_for(small_mat, tmp_path, empty_source())
    daemon.source.front_end.disconnect(7)
    contact = result(run(daemon, tmp_path, "contact-check"))
    selftest = result(run(daemon, tmp_path, "self-test"))
    daemon.close()
    assert contact["source"] == "virtual" and "no contact-test current" in contact["checked"]
    assert contact["open_electrodes"] == [7]
    assert [e["electrode"] for e in contact["electrodes"] if e["ok"]] == [e for e in range(1, 17) if e != 7]
    with_seven = (PROTOCOL.readings == 7).any(axis=1)
    assert [e["usable"] for e in contact["electrodes"]] == [int(((PROTOCOL.readings == e).any(axis=1) & ~with_seven)
                                                                .sum()) for e in range(1, 17)]
    seventh = contact["electrodes"][6]
    assert (seventh["status"], seventh["usable"], seventh["readings"]) == ("open", 0, int(with_seven.sum()))
    assert selftest["passed"] is False and [c["ok"] for c in selftest["checks"]] == [True, True]


def test_capture_reference_refuses_a_loaded_mat_and_replaces_an_empty_ones(small_mat, tmp_path):
    (tmp_path / "loaded").mkdir()
    loaded = daemon_for(small_mat, tmp_path / "loaded")
    before = loaded.monitor.reference.copy()
    refused = run(loaded, tmp_path / "loaded", "capture-reference")
    loaded.close()
    assert refused["state"] == "refused" and refused["result"].startswith("the mat is loaded: it reads")
    assert "the reference is unchanged" in refused["result"]
    assert np.array_equal(loaded.monitor.reference, before, equal_nan=True)

    daemon = daemon_for(small_mat, tmp_path, empty_source())
    before = daemon.monitor.reference.copy()
    done = result(run(daemon, tmp_path, "capture-reference"))
    with Store.open(tmp_path / "appliance.db") as store:
        saved = store.load_state("reference")
    daemon.close()
    assert done["usable"] == 448 and done["peak_mmhg_before"] < 10
    assert not np.array_equal(daemon.monitor.reference, before)                 # a new frame: new noise
    assert np.array_equal(np.array(saved["volts"], dtype=float), daemon.monitor.reference)
    assert saved["layout"] == "grid-4x4"
    fit = done["contact_fit"]                    # the virtual mat's 1 ohm cm^2 contacts on its 8.7 mS saline sheet
    print(fit["contact_over_nominal"], fit["misfit_nominal"], fit["misfit"])
    assert fit["accepted"] and saved["contact_fit"] == fit
    assert 0.005 < fit["contact_over_nominal"][1] < 0.015 and fit["misfit"] < fit["misfit_nominal"]
    in_use = daemon.monitor.model.for_reference(daemon.monitor.reference)
    assert in_use.contact_fit.summary() == fit and in_use.setup.fitted_contact_ohm_m2 is None    # tracked only


def test_capture_reference_refuses_a_light_load_below_the_alert_threshold_and_takes_a_first_one_as_it_is(
        small_mat, tmp_path):
    from appliance.sim.loads import square_load_scene

    (tmp_path / "light").mkdir()
    light = VirtualBedSource(GRID, square_load_scene(100, 100, 30, 70, 40, 2.0), PROTOCOL, frame_interval_s=60.0)
    daemon = daemon_for(small_mat, tmp_path / "light", light)         # a light patient: about 25 mmHg at the peak
    daemon.monitor.reference = empty_source().acquire().volts          # the reference of the mat before they lay down
    before = daemon.monitor.reference.copy()
    peak = daemon.monitor.next_map().peak_kpa / 0.133322
    assert 10 < peak < 32                                               # below the alert threshold
    refused = run(daemon, tmp_path / "light", "capture-reference")
    assert refused["state"] == "refused" and "the mat is loaded" in refused["result"]
    assert "at or above the 10 mmHg an empty mat may show" in refused["result"]
    assert np.array_equal(daemon.monitor.reference, before)
    daemon.monitor.reference = None                                     # no reference yet: nothing to compare with
    first = result(run(daemon, tmp_path / "light", "capture-reference"))
    daemon.close()
    assert first["peak_mmhg_before"] is None and daemon.monitor.reference is not None


def test_calibrate_reports_progress_to_1_and_load_takes_its_file_into_use(small_mat, tmp_path):
    daemon = daemon_for(small_mat, tmp_path)
    running = daemon.monitor.calibration
    shares = recorded_progress(daemon)
    made = result(run(daemon, tmp_path, "calibrate", {"kind": "pressure", "positions": 1}))
    assert made["loads"] == 21 and made["in_use"] is False
    assert shares == sorted(shares) and shares[-1] == 1.0 and len(shares) == 22
    assert daemon.monitor.calibration is running                                  # written, not yet in use
    path = tmp_path / "engineering" / made["file"]
    assert load_pressure_calibration(path).notes["loads"] == 21
    loaded = result(run(daemon, tmp_path, "load", {"what": "calibration", "file": made["file"]}))
    daemon.close()
    assert loaded["in_use"] is True and str(path) in loaded["note"]
    assert daemon.monitor.calibration is not running
    assert daemon.monitor.calibration.notes["made_at"] == load_pressure_calibration(path).notes["made_at"]
    assert daemon.monitor.reference is not None and daemon.maps == 2               # monitoring went on


def test_load_refuses_a_calibration_for_another_mat_or_outside_the_folder_and_keeps_the_running_one(
        small_mat, tmp_path):
    daemon = daemon_for(small_mat, tmp_path)
    running = daemon.monitor.calibration
    square = get_layout("square-16")
    other = dataclasses.replace(running, layout_name=square.name, layout_sha256=layout_fingerprint(square))
    (tmp_path / "engineering").mkdir()
    save_pressure_calibration(tmp_path / "engineering" / "square.json", other)
    for args, message in [({"file": "square.json"}, "was made for layout 'square-16', not for 'grid-4x4'"),
                          ({"file": "missing.json"}, "does not exist"),
                          ({"file": "../appliance.db"}, "file must be a plain file name in engineering/")]:
        refused = run(daemon, tmp_path, "load", {"what": "calibration", **args})
        assert refused["state"] == "refused" and message in refused["result"]
        assert daemon.monitor.calibration is running
    daemon.close()


def test_save_image_writes_the_map_as_a_png(small_mat, tmp_path):
    daemon = daemon_for(small_mat, tmp_path)
    saved = result(run(daemon, tmp_path, "save", {"what": "image"}))
    daemon.close()
    png = (tmp_path / "engineering" / saved["file"]).read_bytes()
    assert png.startswith(b"\x89PNG\r\n\x1a\n") and saved["pixels"] == [16, 16]
    assert saved["peak_mmhg"] > 32                                               # the 6 kPa load of the scene


def test_rebuild_model_reports_progress_and_replaces_the_model_when_built(small_mat, tmp_path):
    daemon = daemon_for(small_mat, tmp_path)
    old = daemon.model
    shares = recorded_progress(daemon)
    rebuilt = result(run(daemon, tmp_path, "rebuild-model"))
    daemon.close()
    assert shares == sorted(shares) and shares[0] == 0.0 and shares[-1] == 1.0 and len(shares) == 5
    assert daemon.model is not old and daemon.monitor.model is daemon.model
    assert daemon.model.setup.key() == old.setup.key()
    assert [p.name for p in (tmp_path / "models").iterdir()] == [f"model-{old.setup.key()}.npz"]
    assert daemon.monitor.model.for_reference(daemon.monitor.reference).contact_fit.accepted   # fitted anew
    assert rebuilt["pixels"] == [16, 16] and daemon.maps == 1


def test_the_daemon_refuses_bad_arguments_and_tasks_that_would_pause_monitoring_too_long(small_mat, tmp_path):
    daemon = daemon_for(small_mat, tmp_path)                 # frames 600 s apart: 3 sets are 30 min
    refused = run(daemon, tmp_path, "acquire", {"averages": 500})
    too_long = run(daemon, tmp_path, "series", {"count": 4, "interval_s": 0})
    daemon.close()
    assert refused["state"] == "refused"
    assert refused["result"] == "acquire: averages must be an integer from 1 to 100, got 500"
    assert too_long["state"] == "refused" and too_long["result"].endswith("at most 30 min: take at most 3 sets")
    assert daemon.maps == 2
    assert not (tmp_path / "engineering").exists()


def test_the_board_runs_its_own_contact_check_and_self_test_and_sends_calibration_to_the_bench(
        small_mat, tmp_path):
    from appliance.service.assemble import assemble
    from appliance.service.config import config_from_mapping

    _, calibration = small_mat
    save_pressure_calibration(tmp_path / "pressure.json", calibration)
    config = config_from_mapping({"monitor": {"layout": "grid-4x4", "source": "hardware", "frame_interval_s": 0.05,
                                              "calibration": str(tmp_path / "pressure.json"),
                                              "data_dir": str(tmp_path), "cache_dir": str(tmp_path / "models")},
                                  "board": {"backend": "emulated"}})
    daemon = assemble(config, say=lambda text: None, live=False)
    try:
        contact = result(run(daemon, tmp_path, "contact-check"))
        selftest = result(run(daemon, tmp_path, "self-test"))
        bench = run(daemon, tmp_path, "calibrate", {"kind": "pressure"})
    finally:
        daemon.close()
    assert contact["source"] == "board" and contact["open_electrodes"] == []
    assert len(contact["pairs"]) == 16 and all(p["impedance_ohm"] < contact["limit_ohm"] for p in contact["pairs"])
    assert selftest["passed"] is True and len(selftest["checks"]) > 3 and all(c["ok"] for c in selftest["checks"])
    assert selftest["contact"]["open_electrodes"] == []
    assert bench["state"] == "refused" and "appliance calibrate pressure --source hardware" in bench["result"]


def test_an_engineer_queues_a_task_from_the_page_and_follows_it_to_done(small_mat, tmp_path, app):
    daemon = daemon_for(small_mat, tmp_path)
    engineer = client_as(app, "engineer")
    csrf = token(engineer, "/engineering")
    answer = engineer.post("/engineering/acquire", data={"averages": "3", "csrf_token": csrf},
                           headers={"Accept": "application/json"})
    assert answer.status_code == 202
    command_id = answer.get_json()["command_id"]
    assert engineer.get(f"/api/commands/{command_id}").get_json()["state"] == "pending"
    assert engineer.post("/engineering/save", data={"what": "image", "csrf_token": csrf}).status_code == 303
    daemon.run(1)
    daemon.close()
    done = engineer.get(f"/api/commands/{command_id}").get_json()
    assert (done["state"], done["progress"], json.loads(done["result"])["sets"]) == ("done", 1.0, 3)
    assert audited(app) == ["engineering task", "engineering task"]
    page = engineer.get("/engineering").get_data(as_text=True)
    assert 'data-command="1"' in page and 'data-command="2"' in page and ".png" in page
