"""Malformed input on every command: exit status 2 and one line naming what is wrong, never a traceback.

A monitor that crashes on a typo, or quietly runs with a nonsense interval, fails
the person in the bed as surely as a wrong alarm. Each case is run in-process and
must be refused before anything expensive is built: a model build would show as a
test that takes minutes. The web screen's forms and uploads are held to the same rule:
a 4xx naming what is wrong, never a 500 and never "nothing changed".

325 command-line cases (layout 13, protocol 11, simulate 26, reconstruct 34, sim load-test 18,
sim run 36, sim replay 14, sim map 20, acquire 24, selftest 5, run 33, calibrate pressure 28,
calibrate sensitivity 11, ward 14, ward-broker 17, hospital 12, provision 6, the parser itself 3), all
exiting 2; 61 web cases (settings 28, patient 7, accounts 8, engineering 18), all answered with a 4xx.
"""

from __future__ import annotations

import signal

import pytest

from appliance.cli import main
from appliance.core.layout_files import layout_to_toml
from appliance.core.named_layouts import get_layout

GOOD_SETTINGS = ["--data-dir", "{t}/data", "--cache-dir", "{t}/cache"]


def _files(t):
    """Bad files of every kind, and a few good ones the bad options are paired with."""
    (t / "folder").mkdir()
    (t / "empty.csv").write_text("")
    (t / "empty.toml").write_text("")
    (t / "garbage.csv").write_text("this is, not\na frame at all\n")
    (t / "garbage.toml").write_text("this = is = not toml [\n")
    (t / "binary.csv").write_bytes(bytes(range(256)) * 4)
    (t / "binary.toml").write_bytes(bytes(range(256)) * 4)
    (t / "columns.csv").write_text("a,b,c\n1,2,3\n")
    (t / "protocol-range.csv").write_text("drive_pos,drive_neg,meas_pos,meas_neg\n1,2,3,99\n")
    (t / "frame-nan.csv").write_text("drive_pos,drive_neg,meas_pos,meas_neg,volts\n1,2,3,4,nan\n")
    (t / "map-nan.csv").write_text("1,2\nnan,4\n")
    (t / "map-ragged.csv").write_text("1,2,3\n4,5\n")
    (t / "layout-types.toml").write_text(layout_to_toml(get_layout("grid-4x4")).replace('"grid-4x4"', "42"))
    (t / "layout-unknown.toml").write_text('colour = "red"\n' + layout_to_toml(get_layout("grid-4x4")))
    (t / "config-types.toml").write_text('[monitor]\nframe_interval_s = "soon"\n')
    (t / "config-unknown.toml").write_text('[monitor]\ncolour = "red"\n')
    (t / "config-nan.toml").write_text("[monitor]\nframe_interval_s = nan\n")
    (t / "scene-types.toml").write_text('[scene]\nduration_s = "long"\n')
    (t / "scene-unknown.toml").write_text('[scene]\ncolour = "red"\n')
    (t / "ward-unknown.toml").write_text('[broker]\nhost = "localhost"\ncolour = "red"\n')
    (t / "ward-types.toml").write_text("[broker]\nhost = 42\n")
    (t / "ward.toml").write_text('[broker]\nhost = "localhost"\n')
    (t / "cal-garbage.json").write_text("{not json")
    (t / "beds-bad.txt").write_text("ward3-bed2\nward3 bed3\n")


LOAD_TEST = ["sim", "load-test", "--area-cm2", "4", "--pressures", "5,10"]
SIM_RUN = ["sim", "run", "--scenario", "supine-still", "--hours", "1", "--out", "{t}/events.jsonl", *GOOD_SETTINGS]
REPLAY = ["sim", "replay", "--scenario", "supine-still", "--out", "{t}/events.jsonl"]
MAP = ["sim", "map", "--cache-dir", "{t}/cache"]
RECON = ["reconstruct", "--layout", "grid-4x4", "--reference", "{t}/ref.csv", "--frame", "{t}/ref.csv",
         "--cache-dir", "{t}/cache"]
ACQUIRE = ["acquire", "--emulated"]
RUN = ["run", *GOOD_SETTINGS, "--check-config"]
PRESSURE = ["calibrate", "pressure", "--layout", "grid-4x4", "--cache-dir", "{t}/cache"]
SENSITIVITY = ["calibrate", "sensitivity", "--layout", "grid-4x4"]
WARD = ["ward", "--check-config", "--data-dir", "{t}/ward"]
WARD_BROKER = ["ward-broker", "--out", "{t}/ward-broker"]
HOSPITAL_CONFIG = ["hospital", "config", "--out", "{t}/engine"]
PROVISION = ["provision", "--config-dir", "{t}/etc", "--data-dir", "{t}/data", "--no-hostname"]

CASES = [
    # layout, protocol: names and layout files
    (["layout", "--layout", "nosuch"], "nosuch"),
    (["layout", "--layout", "grid-0x4"], "0 x 4"),
    (["layout", "--layout", "grid-4x4@0x0"], "grid-4x4@0x0"),
    (["layout", "--layout", "grid-4x4@99999999999999999999x500"], "10 to 10000 mm a side"),
    (["layout", "--layout", "grid-100000x100000"], "100000 x 100000"),
    (["layout", "--layout", "grid-axb"], "grid-axb"),
    (["layout", "--layout", "{t}/missing.toml"], "missing.toml"),
    (["layout", "--layout", "{t}/folder"], "folder"),
    (["layout", "--layout", "{t}/empty.toml"], "empty.toml"),
    (["layout", "--layout", "{t}/garbage.toml"], "garbage.toml"),
    (["layout", "--layout", "{t}/binary.toml"], "binary.toml"),
    (["layout", "--layout", "{t}/layout-types.toml"], "layout-types.toml"),
    (["layout", "--layout", "{t}/layout-unknown.toml"], "colour"),
    (["protocol", "--layout", "grid-4x4", "--kind", "nosuch"], "--kind"),
    (["protocol", "--layout", "circular-16", "--kind", "skip", "--skip", "-1"], "--skip"),
    (["protocol", "--layout", "circular-16", "--kind", "skip", "--skip", "100"], "--skip"),
    (["protocol", "--layout", "circular-16", "--kind", "skip", "--skip", "99999"], "--skip"),
    (["protocol", "--layout", "circular-16", "--kind", "skip", "--skip", "x"], "--skip"),
    (["protocol", "--layout", "grid-4x4", "--kind", "local", "--reach", "-1"], "--reach"),
    (["protocol", "--layout", "grid-4x4", "--kind", "local", "--reach", "0"], "--reach"),
    (["protocol", "--layout", "grid-4x4", "--kind", "local", "--reach", "nan"], "--reach"),
    (["protocol", "--layout", "grid-4x4", "--kind", "local", "--reach", "inf"], "--reach"),
    (["protocol", "--layout", "grid-4x4", "--kind", "local", "--reach", "1e300"], "--reach"),
    (["protocol", "--layout", "grid-4x4", "--kind", "adjacent", "--reach", "2"], "--reach"),
    # simulate
    (["simulate", "--layout", "grid-4x4", "--density", "0"], "--density"),
    (["simulate", "--layout", "grid-4x4", "--density", "-1"], "--density"),
    (["simulate", "--layout", "grid-4x4", "--density", "nan"], "--density"),
    (["simulate", "--layout", "grid-4x4", "--density", "inf"], "--density"),
    (["simulate", "--layout", "grid-4x4", "--density", "1e9"], "--density"),
    (["simulate", "--layout", "grid-4x4", "--current-ma", "0"], "--current-ma"),
    (["simulate", "--layout", "grid-4x4", "--current-ma", "-1"], "--current-ma"),
    (["simulate", "--layout", "grid-4x4", "--current-ma", "nan"], "--current-ma"),
    (["simulate", "--layout", "grid-4x4", "--current-ma", "inf"], "--current-ma"),
    (["simulate", "--layout", "grid-4x4", "--current-ma", "1e300"], "--current-ma"),
    (["simulate", "--layout", "grid-4x4", "--inclusion", "rect:nan,50,10,10,0.5"], "rect:nan"),
    (["simulate", "--layout", "grid-4x4", "--inclusion", "rect:50,50,-10,10,0.5"], "rect:50,50,-10"),
    (["simulate", "--layout", "grid-4x4", "--inclusion", "disc:50,50,inf,0.5"], "disc:50,50,inf"),
    (["simulate", "--layout", "grid-4x4", "--inclusion", "tri:1,2,3"], "tri:1,2,3"),
    (["simulate", "--layout", "grid-4x4", "--inclusion", "rect:5000,5000,10,10,0.5"], "rect:5000,5000"),
    (["simulate", "--layout", "grid-4x4", "--inclusion", "rect:1e300,50,10,10,0.5"], "rect:1e300"),
    (["simulate", "--layout", "grid-4x4", "--inclusion", "disc:50,50,10,1e300"], "disc:50,50,10,1e300"),
    (["simulate", "--layout", "grid-4x4", "--protocol", "{t}/missing.csv"], "missing.csv"),
    (["simulate", "--layout", "grid-4x4", "--protocol", "{t}/folder"], "folder"),
    (["simulate", "--layout", "grid-4x4", "--protocol", "{t}/empty.csv"], "empty.csv"),
    (["simulate", "--layout", "grid-4x4", "--protocol", "{t}/garbage.csv"], "garbage.csv"),
    (["simulate", "--layout", "grid-4x4", "--protocol", "{t}/binary.csv"], "binary.csv"),
    (["simulate", "--layout", "grid-4x4", "--protocol", "{t}/columns.csv"], "columns.csv"),
    (["simulate", "--layout", "grid-4x4", "--protocol", "{t}/protocol-range.csv"], "protocol-range.csv"),
    (["simulate", "--layout", "grid-4x4", "--out", "{t}/nofolder/frame.csv"], "nofolder"),
    (["simulate", "--layout", "grid-4x4", "--out", "{t}/folder"], "folder"),
    # reconstruct
    ([*RECON, "--out", "{t}/nofolder/img.csv"], "nofolder"),
    ([*RECON, "--out", "{t}/folder"], "folder"),
    ([*RECON, "--out", "{t}/img.jpg"], "img.jpg"),
    ([*RECON, "--out", "{t}/img.csv", "--segment", "{t}/nofolder/seg.csv"], "nofolder"),
    ([*RECON, "--out", "{t}/img.csv", "--algorithm", "nosuch"], "nosuch"),
    ([*RECON, "--out", "{t}/img.csv", "--iterate", "sometimes"], "--iterate"),
    ([*RECON, "--out", "{t}/img.csv", "--noise", "a,b"], "--noise"),
    ([*RECON, "--out", "{t}/img.csv", "--noise", "-1,0"], "--noise"),
    ([*RECON, "--out", "{t}/img.csv", "--noise", "nan,1e-4"], "--noise"),
    ([*RECON, "--out", "{t}/img.csv", "--noise", "1e300,1e-4"], "--noise"),
    ([*RECON, "--out", "{t}/img.csv", "--pixels", "0x0"], "--pixels"),
    ([*RECON, "--out", "{t}/img.csv", "--pixels", "-4x4"], "--pixels"),
    ([*RECON, "--out", "{t}/img.csv", "--pixels", "4.5x4"], "--pixels"),
    ([*RECON, "--out", "{t}/img.csv", "--pixels", "100000x100000"], "--pixels"),
    ([*RECON, "--out", "{t}/img.csv", "--pixels", "inf x 4"], "--pixels"),
    ([*RECON, "--out", "{t}/img.csv", "--density", "0"], "--density"),
    ([*RECON, "--out", "{t}/img.csv", "--density", "nan"], "--density"),
    ([*RECON, "--out", "{t}/img.csv", "--density", "-2"], "--density"),
    ([*RECON, "--out", "{t}/img.csv", "--pressure", "{t}/cal.json", "--normalise"], "--normalise"),
    ([*RECON, "--out", "{t}/img.csv", "--temperature-c", "20"], "--temperature-c"),
    ([*RECON, "--out", "{t}/img.csv", "--pressure", "{t}/cal.json", "--temperature-c", "1e300"], "--temperature-c"),
    ([*RECON, "--out", "{t}/img.csv", "--pressure", "{t}/missing.json"], "missing.json"),
    ([*RECON, "--out", "{t}/img.csv", "--pressure", "{t}/cal-garbage.json"], "cal-garbage.json"),
    ([*RECON, "--out", "{t}/img.csv", "--pressure", "{t}/folder"], "folder"),
    ([*RECON, "--out", "{t}/img.csv", "--calibration", "{t}/missing.csv"], "missing.csv"),
    ([*RECON, "--out", "{t}/img.csv", "--calibration", "{t}/folder"], "folder"),
    (["reconstruct", "--layout", "grid-4x4", "--reference", "{t}/missing.csv", "--frame", "{t}/ref.csv",
      "--out", "{t}/img.csv"], "missing.csv"),
    (["reconstruct", "--layout", "grid-4x4", "--reference", "{t}/folder", "--frame", "{t}/ref.csv",
      "--out", "{t}/img.csv"], "folder"),
    (["reconstruct", "--layout", "grid-4x4", "--reference", "{t}/empty.csv", "--frame", "{t}/ref.csv",
      "--out", "{t}/img.csv"], "empty.csv"),
    (["reconstruct", "--layout", "grid-4x4", "--reference", "{t}/binary.csv", "--frame", "{t}/ref.csv",
      "--out", "{t}/img.csv"], "binary.csv"),
    (["reconstruct", "--layout", "grid-4x4", "--reference", "{t}/ref.csv", "--frame", "{t}/garbage.csv",
      "--out", "{t}/img.csv"], "garbage.csv"),
    (["reconstruct", "--layout", "grid-4x4", "--reference", "{t}/ref.csv", "--frame", "{t}/columns.csv",
      "--out", "{t}/img.csv"], "columns.csv"),
    (["reconstruct", "--layout", "grid-4x4", "--reference", "{t}/ref.csv", "--frame", "{t}/frame-nan.csv",
      "--out", "{t}/img.csv"], "frame-nan"),
    (["reconstruct", "--layout", "grid-4x4", "--reference", "{t}/ref.csv", "--frame", "{t}/data.mat",
      "--out", "{t}/img.csv"], "data.mat"),
    # sim load-test
    ([*LOAD_TEST, "--area-cm2", "0"], "--area-cm2"),
    ([*LOAD_TEST, "--area-cm2", "-4"], "--area-cm2"),
    ([*LOAD_TEST, "--area-cm2", "nan"], "--area-cm2"),
    ([*LOAD_TEST, "--area-cm2", "1000"], "--area-cm2"),
    (["sim", "load-test", "--area-cm2", "4", "--pressures", ""], "--pressures"),
    (["sim", "load-test", "--area-cm2", "4", "--pressures", "a,b"], "--pressures"),
    (["sim", "load-test", "--area-cm2", "4", "--pressures", "5,nan"], "--pressures"),
    (["sim", "load-test", "--area-cm2", "4", "--pressures", "5,inf"], "--pressures"),
    (["sim", "load-test", "--area-cm2", "4", "--pressures", "-5"], "--pressures"),
    (["sim", "load-test", "--area-cm2", "4", "--pressures", "5,1000"], "--pressures"),
    ([*LOAD_TEST, "--density", "0"], "--density"),
    ([*LOAD_TEST, "--density", "nan"], "--density"),
    ([*LOAD_TEST, "--temperature-c", "nan"], "--temperature-c"),
    ([*LOAD_TEST, "--temperature-c", "-300"], "--temperature-c"),
    ([*LOAD_TEST, "--temperature-c", "1e300"], "--temperature-c"),
    ([*LOAD_TEST, "--drift-c-per-step", "inf"], "--drift-c-per-step"),
    ([*LOAD_TEST, "--drift-c-per-step", "1e300"], "--drift-c-per-step"),
    ([*LOAD_TEST, "--layout", "nosuch"], "nosuch"),
    # sim run
    ([*SIM_RUN, "--hours", "0"], "--hours"),
    ([*SIM_RUN, "--hours", "-1"], "--hours"),
    ([*SIM_RUN, "--hours", "nan"], "--hours"),
    ([*SIM_RUN, "--hours", "inf"], "--hours"),
    ([*SIM_RUN, "--hours", "1000"], "--hours"),
    ([*SIM_RUN, "--hours", "1e300"], "--hours"),
    ([*SIM_RUN, "--interval", "0"], "--interval"),
    ([*SIM_RUN, "--interval", "-60"], "--interval"),
    ([*SIM_RUN, "--interval", "nan"], "--interval"),
    ([*SIM_RUN, "--interval", "inf"], "--interval"),
    ([*SIM_RUN, "--interval", "1e-300"], "--interval"),
    ([*SIM_RUN, "--interval", "1e200"], "--interval"),
    ([*SIM_RUN, "--seed", "99999999999"], "--seed"),
    ([*SIM_RUN, "--acknowledge-after-min", "-1"], "--acknowledge-after-min"),
    ([*SIM_RUN, "--acknowledge-after-min", "nan"], "--acknowledge-after-min"),
    ([*SIM_RUN, "--acknowledge-after-min", "1e300"], "--acknowledge-after-min"),
    ([*SIM_RUN, "--seed", "-1"], "--seed"),
    ([*SIM_RUN, "--seed", "1.5"], "--seed"),
    ([*SIM_RUN, "--scenario", "nosuch"], "nosuch"),
    ([*SIM_RUN, "--scenario", "{t}/missing.toml"], "missing.toml"),
    ([*SIM_RUN, "--scenario", "{t}/folder"], "folder"),
    ([*SIM_RUN, "--scenario", "{t}/empty.toml"], "empty.toml"),
    ([*SIM_RUN, "--scenario", "{t}/garbage.toml"], "garbage.toml"),
    ([*SIM_RUN, "--scenario", "{t}/binary.toml"], "binary.toml"),
    ([*SIM_RUN, "--scenario", "{t}/scene-types.toml"], "scene-types.toml"),
    ([*SIM_RUN, "--scenario", "{t}/scene-unknown.toml"], "colour"),
    ([*SIM_RUN, "--config", "{t}/missing.toml"], "missing.toml"),
    ([*SIM_RUN, "--config", "{t}/folder"], "folder"),
    ([*SIM_RUN, "--config", "{t}/garbage.toml"], "garbage.toml"),
    ([*SIM_RUN, "--config", "{t}/binary.toml"], "binary.toml"),
    ([*SIM_RUN, "--config", "{t}/config-types.toml"], "frame_interval_s"),
    ([*SIM_RUN, "--config", "{t}/config-unknown.toml"], "colour"),
    ([*SIM_RUN, "--config", "{t}/config-nan.toml"], "frame_interval_s"),
    ([*SIM_RUN, "--layout", "nosuch"], "nosuch"),
    ([*SIM_RUN, "--out", "{t}/folder"], "folder"),
    ([*SIM_RUN, "--out", "{t}/empty.csv/events.jsonl"], "empty.csv"),
    # sim replay
    ([*REPLAY, "--hours", "0"], "--hours"),
    ([*REPLAY, "--hours", "nan"], "--hours"),
    ([*REPLAY, "--hours", "inf"], "--hours"),
    ([*REPLAY, "--hours", "1e300"], "--hours"),
    ([*REPLAY, "--interval", "0"], "--interval"),
    ([*REPLAY, "--interval", "nan"], "--interval"),
    ([*REPLAY, "--interval", "inf"], "--interval"),
    ([*REPLAY, "--interval", "1e-300"], "--interval"),
    ([*REPLAY, "--interval", "1e200"], "--interval"),
    ([*REPLAY, "--scenario", "nosuch"], "nosuch"),
    ([*REPLAY, "--scenario", "{t}/garbage.toml"], "garbage.toml"),
    ([*REPLAY, "--config", "{t}/config-unknown.toml"], "colour"),
    ([*REPLAY, "--layout", "nosuch"], "nosuch"),
    ([*REPLAY, "--out", "{t}/folder"], "folder"),
    # sim map
    ([*MAP, "--pitch-mm", "10", "--out", "{t}/o.csv"], "--map"),
    ([*MAP, "--map", "{t}/missing.csv", "--pitch-mm", "10", "--out", "{t}/o.csv"], "missing.csv"),
    ([*MAP, "--map", "{t}/folder", "--pitch-mm", "10", "--out", "{t}/o.csv"], "folder"),
    ([*MAP, "--map", "{t}/empty.csv", "--pitch-mm", "10", "--out", "{t}/o.csv"], "empty.csv"),
    ([*MAP, "--map", "{t}/garbage.csv", "--pitch-mm", "10", "--out", "{t}/o.csv"], "garbage.csv"),
    ([*MAP, "--map", "{t}/binary.csv", "--pitch-mm", "10", "--out", "{t}/o.csv"], "binary.csv"),
    ([*MAP, "--map", "{t}/map-nan.csv", "--pitch-mm", "10", "--out", "{t}/o.csv"], "map-nan.csv"),
    ([*MAP, "--map", "{t}/map-ragged.csv", "--pitch-mm", "10", "--out", "{t}/o.csv"], "map-ragged.csv"),
    ([*MAP, "--map", "{t}/map.csv", "--pitch-mm", "0", "--out", "{t}/o.csv"], "--pitch-mm"),
    ([*MAP, "--map", "{t}/map.csv", "--pitch-mm", "nan", "--out", "{t}/o.csv"], "--pitch-mm"),
    ([*MAP, "--map", "{t}/map.csv", "--pitch-mm", "inf", "--out", "{t}/o.csv"], "--pitch-mm"),
    ([*MAP, "--map", "{t}/map.csv", "--pitch-mm", "x", "--out", "{t}/o.csv"], "--pitch-mm"),
    ([*MAP, "--map", "{t}/map.csv", "--pitch-mm", "10"], "--out"),
    ([*MAP, "--map", "{t}/map.csv", "--pitch-mm", "10", "--out", "{t}/o.txt"], "o.txt"),
    ([*MAP, "--map", "{t}/map.csv", "--pitch-mm", "10", "--out", "{t}/nofolder/o.csv"], "nofolder"),
    ([*MAP, "--map", "{t}/map.csv", "--pitch-mm", "10", "--out", "{t}/map.csv"], "map.csv"),
    ([*MAP, "--map", "{t}/map.csv", "--pitch-mm", "10", "--out", "{t}/o.csv", "--seed", "-1"], "--seed"),
    ([*MAP, "--map", "{t}/map.csv", "--pitch-mm", "10", "--out", "{t}/o.csv", "--seed", "99999999999"], "--seed"),
    ([*MAP, "--map", "{t}/map.csv", "--pitch-mm", "10", "--out", "{t}/o.csv", "--layout", "nosuch"], "nosuch"),
    ([*MAP, "--map", "{t}/map.csv", "--pitch-mm", "10", "--out", "{t}/o.csv", "--calibration", "{t}/missing.json"],
     "missing.json"),
    # acquire, selftest
    ([*ACQUIRE, "--out", "{t}/f.csv", "--average", "0"], "--average"),
    ([*ACQUIRE, "--out", "{t}/f.csv", "--average", "-3"], "--average"),
    ([*ACQUIRE, "--out", "{t}/f.csv", "--average", "100000"], "--average"),
    ([*ACQUIRE, "--out", "{t}/f.csv", "--series", "0"], "--series"),
    ([*ACQUIRE, "--out", "{t}/f.csv", "--series", "61"], "--series"),
    ([*ACQUIRE, "--out", "{t}/f.csv", "--series", "2", "--interval", "-1"], "--interval"),
    ([*ACQUIRE, "--out", "{t}/f.csv", "--series", "2", "--interval", "nan"], "--interval"),
    ([*ACQUIRE, "--out", "{t}/f.csv", "--series", "2", "--interval", "1e200"], "--interval"),
    ([*ACQUIRE, "--out", "{t}/f.csv", "--interval", "-1"], "--interval"),
    ([*ACQUIRE, "--out", "{t}/f.csv", "--order", "random"], "--order"),
    ([*ACQUIRE, "--out", "{t}/nofolder/f.csv"], "nofolder"),
    ([*ACQUIRE, "--out", "{t}/folder"], "folder"),
    ([*ACQUIRE, "--out", "{t}/f.png"], "f.png"),
    ([*ACQUIRE, "--out", "{t}/f.csv", "--protocol", "{t}/missing.csv"], "missing.csv"),
    ([*ACQUIRE, "--out", "{t}/f.csv", "--protocol", "{t}/garbage.csv"], "garbage.csv"),
    ([*ACQUIRE, "--out", "{t}/f.csv", "--config", "{t}/missing.toml"], "missing.toml"),
    ([*ACQUIRE, "--out", "{t}/f.csv", "--config", "{t}/garbage.toml"], "garbage.toml"),
    ([*ACQUIRE, "--out", "{t}/f.csv", "--config", "{t}/folder"], "folder"),
    ([*ACQUIRE, "--out", "{t}/f.csv", "--profile", "nosuch"], "nosuch"),
    ([*ACQUIRE, "--out", "{t}/f.csv", "--layout", "nosuch"], "nosuch"),
    ([*ACQUIRE, "--out", "{t}/f.csv", "--seed", "-1"], "--seed"),
    ([*ACQUIRE, "--out", "{t}/f.csv", "--inclusion", "rect:1,2"], "rect:1,2"),
    ([*ACQUIRE, "--out", "{t}/f.csv", "--inclusion", "disc:50,50,1e300,0.5"], "disc:50,50,1e300"),
    (["acquire", "--out", "{t}/f.csv", "--inclusion", "rect:50,50,10,10,0.5"], "--emulated"),
    (["selftest", "--emulated", "--profile", "nosuch"], "nosuch"),
    (["selftest", "--emulated", "--layout", "nosuch"], "nosuch"),
    (["selftest", "--emulated", "--config", "{t}/binary.toml"], "binary.toml"),
    (["selftest", "--emulated", "--config", "{t}/config-unknown.toml"], "colour"),
    (["selftest", "--emulated", "--inclusion", "disc:a,b,c,d"], "disc:a,b,c,d"),
    # run
    ([*RUN, "--frames", "0"], "--frames"),
    ([*RUN, "--frames", "-5"], "--frames"),
    ([*RUN, "--frames", "x"], "--frames"),
    ([*RUN, "--frames", "99999999999"], "--frames"),
    ([*RUN, "--interval", "0"], "--interval"),
    ([*RUN, "--interval", "-1"], "--interval"),
    ([*RUN, "--interval", "nan"], "--interval"),
    ([*RUN, "--interval", "inf"], "--interval"),
    ([*RUN, "--interval", "1e-300"], "--interval"),
    ([*RUN, "--interval", "1e200"], "--interval"),
    ([*RUN, "--speed", "1e300"], "--speed"),
    ([*RUN, "--speed", "-1"], "--speed"),
    ([*RUN, "--speed", "nan"], "--speed"),
    ([*RUN, "--speed", "inf"], "--speed"),
    ([*RUN, "--seed", "-1"], "--seed"),
    ([*RUN, "--screen", "abc"], "--screen"),
    ([*RUN, "--screen", "0"], "--screen"),
    ([*RUN, "--screen", "70000"], "--screen"),
    ([*RUN, "--config", "{t}/missing.toml"], "missing.toml"),
    ([*RUN, "--config", "{t}/folder"], "folder"),
    ([*RUN, "--config", "{t}/garbage.toml"], "garbage.toml"),
    ([*RUN, "--config", "{t}/binary.toml"], "binary.toml"),
    ([*RUN, "--config", "{t}/config-types.toml"], "frame_interval_s"),
    ([*RUN, "--config", "{t}/config-unknown.toml"], "colour"),
    ([*RUN, "--config", "{t}/config-nan.toml"], "frame_interval_s"),
    ([*RUN, "--scenario", "nosuch"], "nosuch"),
    ([*RUN, "--scenario", "{t}/scene-types.toml"], "scene-types.toml"),
    ([*RUN, "--layout", "nosuch"], "nosuch"),
    ([*RUN, "--layout", "{t}/garbage.toml"], "garbage.toml"),
    ([*RUN, "--calibration", "{t}/missing.json"], "missing.json"),
    ([*RUN, "--calibration", "{t}/folder"], "folder"),
    ([*RUN, "--data-dir", "{t}/empty.csv"], "empty.csv"),
    ([*RUN, "--cache-dir", "{t}/empty.csv"], "empty.csv"),
    # calibrate
    ([*PRESSURE, "--out", "{t}/c.json", "--positions", "0"], "--positions"),
    ([*PRESSURE, "--out", "{t}/c.json", "--averages", "0"], "--averages"),
    ([*PRESSURE, "--out", "{t}/c.json", "--positions", "100000"], "--positions"),
    ([*PRESSURE, "--out", "{t}/c.json", "--averages", "100000"], "--averages"),
    ([*PRESSURE, "--out", "{t}/c.json", "--pressures", "a"], "--pressures"),
    ([*PRESSURE, "--out", "{t}/c.json", "--pressures", "-1,5"], "--pressures"),
    ([*PRESSURE, "--out", "{t}/c.json", "--pressures", "nan"], "--pressures"),
    ([*PRESSURE, "--out", "{t}/c.json", "--pressures", "5,inf"], "--pressures"),
    ([*PRESSURE, "--out", "{t}/c.json", "--pressures", "5,1e300"], "--pressures"),
    ([*PRESSURE, "--out", "{t}/c.json", "--pixels", "0x0"], "--pixels"),
    ([*PRESSURE, "--out", "{t}/c.json", "--pixels", "axb"], "--pixels"),
    ([*PRESSURE, "--out", "{t}/c.json", "--density", "0"], "--density"),
    ([*PRESSURE, "--out", "{t}/c.json", "--density", "nan"], "--density"),
    ([*PRESSURE, "--out", "{t}/c.json", "--seed", "-1"], "--seed"),
    ([*PRESSURE, "--out", "{t}/c.json", "--algorithm", "nosuch"], "nosuch"),
    ([*PRESSURE, "--out", "{t}/c.json", "--source", "nowhere"], "--source"),
    ([*PRESSURE, "--out", "{t}/c.json", "--layout", "nosuch"], "nosuch"),
    ([*PRESSURE, "--out", "{t}/c.json", "--profile", "nosuch"], "nosuch"),
    ([*PRESSURE, "--out", "{t}/c.json", "--config", "{t}/garbage.toml"], "garbage.toml"),
    ([*PRESSURE, "--out", "{t}/nofolder/c.json"], "nofolder"),
    ([*PRESSURE, "--out", "{t}/folder"], "folder"),
    ([*PRESSURE, "--out", "{t}/c.json", "--maps", "{t}/missing"], "--maps"),
    ([*PRESSURE, "--out", "{t}/c.json", "--maps", "{t}/folder"], "--subjects"),
    ([*PRESSURE, "--out", "{t}/c.json", "--maps", "{t}/folder", "--subjects", "a"], "--subjects"),
    ([*PRESSURE, "--out", "{t}/c.json", "--maps", "{t}/folder", "--subjects", "1",
      "--frames-per-posture", "0"], "--frames-per-posture"),
    ([*PRESSURE, "--out", "{t}/c.json", "--maps", "{t}/folder", "--subjects", "1",
      "--frames-per-posture", "100000"], "--frames-per-posture"),
    ([*PRESSURE, "--out", "{t}/c.json", "--maps", "{t}/folder", "--subjects", "1", "--source", "hardware"],
     "--maps"),
    ([*PRESSURE, "--out", "{t}/c.json", "--subjects", "1"], "--subjects"),
    ([*SENSITIVITY, "--out", "{t}/s.csv", "--side-mm", "0"], "--side-mm"),
    ([*SENSITIVITY, "--out", "{t}/s.csv", "--side-mm", "nan"], "--side-mm"),
    ([*SENSITIVITY, "--out", "{t}/s.csv", "--side-mm", "inf"], "--side-mm"),
    ([*SENSITIVITY, "--out", "{t}/s.csv", "--side-mm", "1e300"], "--side-mm"),
    ([*SENSITIVITY, "--out", "{t}/s.csv", "--pressure-kpa", "-1"], "--pressure-kpa"),
    ([*SENSITIVITY, "--out", "{t}/s.csv", "--pressure-kpa", "nan"], "--pressure-kpa"),
    ([*SENSITIVITY, "--out", "{t}/s.csv", "--pressure-kpa", "inf"], "--pressure-kpa"),
    ([*SENSITIVITY, "--out", "{t}/s.csv", "--pressure-kpa", "1e300"], "--pressure-kpa"),
    ([*SENSITIVITY, "--out", "{t}/s.csv", "--pixels", "0x4"], "--pixels"),
    ([*SENSITIVITY, "--out", "{t}/nofolder/s.csv"], "nofolder"),
    ([*SENSITIVITY, "--out", "{t}/folder"], "folder"),
    # ward
    ([*WARD, "--config", "{t}/missing.toml"], "missing.toml"),
    ([*WARD, "--config", "{t}/folder"], "folder"),
    ([*WARD, "--config", "{t}/empty.toml"], "empty.toml"),
    ([*WARD, "--config", "{t}/garbage.toml"], "garbage.toml"),
    ([*WARD, "--config", "{t}/binary.toml"], "binary.toml"),
    ([*WARD, "--config", "{t}/ward-unknown.toml"], "colour"),
    ([*WARD, "--config", "{t}/ward-types.toml"], "host"),
    ([*WARD, "--config", "{t}/ward.toml", "--listen", "abc"], "--listen"),
    ([*WARD, "--config", "{t}/ward.toml", "--listen", "0"], "--listen"),
    ([*WARD, "--config", "{t}/ward.toml", "--listen", "99999"], "--listen"),
    ([*WARD, "--config", "{t}/ward.toml", "--threads", "0"], "--threads"),
    ([*WARD, "--config", "{t}/ward.toml", "--threads", "100000"], "--threads"),
    ([*WARD, "--config", "{t}/ward.toml", "--threads", "x"], "--threads"),
    ([*WARD, "--config", "{t}/ward.toml", "--data-dir", "{t}/empty.csv"], "empty.csv"),
    # ward-broker
    (WARD_BROKER, "no beds"),
    ([*WARD_BROKER, "--bed", "ward3/bed1"], "ward3/bed1"),
    ([*WARD_BROKER, "--bed", "ward3+bed1"], "ward3+bed1"),
    ([*WARD_BROKER, "--bed", "ward3 bed1"], "ward3 bed1"),
    ([*WARD_BROKER, "--bed", "b" * 65], "b" * 65),
    ([*WARD_BROKER, "--bed", "bed1", "--bed", "bed1"], "given twice"),
    ([*WARD_BROKER, "--bed", "bed1", "--station", "bed1"], "also a bed id"),
    ([*WARD_BROKER, "--bed", "bed1", "--topic-prefix", "ward/#"], "--topic-prefix"),
    ([*WARD_BROKER, "--bed", "bed1", "--beds-file", "{t}/missing.txt"], "missing.txt"),
    ([*WARD_BROKER, "--bed", "bed1", "--beds-file", "{t}/beds-bad.txt"], "line 2"),
    ([*WARD_BROKER, "--bed", "bed1", "--beds-file", "{t}/binary.csv"], "binary.csv"),
    (["ward-broker", "--out", "{t}/empty.csv", "--bed", "bed1"], "empty.csv"),
    (["ward-broker", "--out", "{t}/nofolder/ward", "--bed", "bed1"], "nofolder"),
    ([*WARD_BROKER, "--bed", "bed1", "--listener", "x"], "--listener"),
    ([*WARD_BROKER, "--bed", "bed1", "--listener", "70000"], "--listener"),
    ([*WARD_BROKER, "--bed", "bed1", "--certfile", "{t}/ref.csv"], "--certfile"),
    ([*WARD_BROKER, "--bed", "bed1", "--broker-user", "no-such-account"], "no-such-account"),
    # hospital
    ([*HOSPITAL_CONFIG, "--description", "{t}/missing.toml"], "missing.toml"),
    ([*HOSPITAL_CONFIG, "--description", "{t}/folder"], "folder"),
    ([*HOSPITAL_CONFIG, "--description", "{t}/empty.toml"], "[hospital] is missing"),
    ([*HOSPITAL_CONFIG, "--description", "{t}/garbage.toml"], "garbage.toml"),
    ([*HOSPITAL_CONFIG, "--description", "{t}/binary.toml"], "binary.toml"),
    (["hospital", "config", "--description", "{t}/hospital.toml", "--out", "{t}/empty.csv"], "empty.csv"),
    (["hospital", "config", "--description", "{t}/hospital.toml", "--out", "{t}/nofolder/engine"], "nofolder"),
    (["hospital", "streams", "--description", "{t}/hospital.toml", "--secrets", "{t}/folder"],
     "hospital-admin.password does not exist"),
    (["hospital", "notify", "--description", "{t}/hospital.toml", "--secrets", "{t}/folder", "--notifier", "pagers"],
     "no [[notifier]] named 'pagers'"),
    (["hospital", "start-local", "--beds", "0"], "--beds"),
    (["hospital", "start-local", "--beds", "x"], "--beds"),
    (["hospital"], "HOSPITAL_COMMAND"),
    # provision
    ([*PROVISION, "--setup", "{t}/missing.toml"], "missing.toml"),
    ([*PROVISION, "--setup", "{t}/folder"], "folder"),
    ([*PROVISION, "--setup", "{t}/empty.toml"], "empty.toml"),
    ([*PROVISION, "--setup", "{t}/garbage.toml"], "garbage.toml"),
    ([*PROVISION, "--setup", "{t}/binary.toml"], "binary.toml"),
    ([*PROVISION, "--setup", "{t}/scene-unknown.toml"], "scene"),
    # the command line itself
    (["nosuch"], "nosuch"),
    (["sim", "nosuch"], "nosuch"),
    (["calibrate"], "CALIBRATE_COMMAND"),
]


@pytest.fixture(scope="module")
def t(tmp_path_factory):
    """One folder of bad files and the good ones they are paired with, made once for all the cases."""
    t = tmp_path_factory.mktemp("bad-input")
    _files(t)
    assert main(["simulate", "--layout", "grid-4x4", "--out", str(t / "ref.csv")]) == 0
    (t / "map.csv").write_text("0,40\n40,0\n")
    (t / "data.mat").write_bytes(b"not a mat file")
    (t / "hospital.toml").write_text('[hospital]\ncluster = "c"\nstore_dir = "store"\nreplicas = 1\n'
                                     '[[node]]\nname = "n1"\nhost = "127.0.0.1"\n'
                                     '[[ward]]\nname = "w"\nbeds = ["b"]\nstations = ["s"]\n')
    return t


class _TooSlow(Exception):
    """A refusal that was not made before something slow started."""


@pytest.fixture
def deadline():
    """Fail a case that runs on for long: bad input must be refused before any model is built."""
    def stop(signum, frame):
        raise _TooSlow("still running: the bad input was not refused before the slow part")

    old = signal.signal(signal.SIGALRM, stop)
    signal.alarm(60)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, old)


def _ids():
    return [" ".join(a for a in args if not a.startswith("{t}/data") and not a.startswith("{t}/cache"))[:80]
            for args, _ in CASES]


@pytest.mark.parametrize(("args", "named"), CASES, ids=_ids())
def test_bad_input_exits_2_with_one_line_naming_it(capsys, t, deadline, args, named):
    argv = [a.replace("{t}", str(t)) for a in args]
    try:
        code = main(argv)
    except SystemExit as exc:       # argparse's own refusals
        code = exc.code
    _, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert code == 2, f"exit status {code}; stderr: {err[-500:]}"
    assert "Traceback" not in err
    assert lines and (lines[-1].startswith("appliance: error: ")
                      or (lines[-1].startswith("appliance") and ": error: " in lines[-1])), lines
    assert _names(lines[-1], named, argv), lines[-1]


def _names(line: str, named: str, argv: list[str]) -> bool:
    """Whether the message names what is wrong: the option or file expected, or for an option the bad value."""
    if named in line:
        return True
    return named.startswith("--") and (named.lstrip("-") in line or argv[-1] in line)


# The web screen: each malformed form, JSON body or upload is refused with a 4xx and a message naming it.

WEB_CASES = [
    # (role, path, form or None, JSON body or None, named)
    ("nurse", "/settings/patient", {"threshold_mmhg": "nan"}, None, "threshold_mmhg"),
    ("nurse", "/settings/patient", {"threshold_mmhg": "inf"}, None, "threshold_mmhg"),
    ("nurse", "/settings/patient", {"threshold_mmhg": "-inf"}, None, "threshold_mmhg"),
    ("nurse", "/settings/patient", {"threshold_mmhg": "1e400"}, None, "threshold_mmhg"),
    ("nurse", "/settings/patient", {"threshold_mmhg": "-1"}, None, "threshold_mmhg"),
    ("nurse", "/settings/patient", {"threshold_mmhg": ""}, None, "threshold_mmhg"),
    ("nurse", "/settings/patient", {"threshold_mmhg": "abc"}, None, "threshold_mmhg"),
    ("nurse", "/settings/patient", {"relief_min": "inf"}, None, "relief_min"),
    ("nurse", "/settings/patient", {"curve": "nosuch"}, None, "curve"),
    ("nurse", "/settings/patient", {"colour": "red"}, None, "colour"),
    ("nurse", "/settings/patient", None, [1, 2], "JSON object"),
    ("nurse", "/settings/patient", None, {"threshold_mmhg": None}, "threshold_mmhg"),
    ("nurse", "/settings/patient", None, {"threshold_mmhg": True}, "threshold_mmhg"),
    ("nurse", "/settings/patient", None, {"threshold_mmhg": [40]}, "threshold_mmhg"),
    ("nurse", "/settings/patient", None, {"threshold_mmhg": 1e308}, "threshold_mmhg"),
    ("engineer", "/settings/bed", {"layout": "nosuch"}, None, "layout"),
    ("engineer", "/settings/bed", {"bed_id": ""}, None, "bed_id"),
    ("engineer", "/settings/bed", None, {"layout": 5}, "layout"),
    ("admin", "/settings/policy", {"threshold_mmhg_low": "nan", "threshold_mmhg_high": "40"}, None, "threshold_mmhg"),
    ("admin", "/settings/policy", {"threshold_mmhg_low": "50", "threshold_mmhg_high": "40"}, None, "threshold_mmhg"),
    ("admin", "/settings/policy", None, {"threshold_mmhg": ["a", "b"]}, "threshold_mmhg"),
    ("admin", "/settings/policy", None, [1], "JSON object"),
    ("engineer", "/settings/file", {"file": (b"\xff\xfe", "s.toml")}, None, "s.toml"),
    ("engineer", "/settings/file", {"file": (b"x = = 1", "s.toml")}, None, "s.toml"),
    ("engineer", "/settings/file", {"file": (b"[alerts]\nthreshold_mmhg = nan\n", "s.toml")}, None, "threshold_mmhg"),
    ("engineer", "/settings/file", {"file": (b"[alerts]\nthreshold_mmhg = inf\n", "s.toml")}, None, "threshold_mmhg"),
    ("engineer", "/settings/file", {"file": (b"[alerts]\nthreshold_mmhg = 'a'\n", "s.toml")}, None, "threshold_mmhg"),
    ("engineer", "/settings/file", {"file": (b"[nosuch]\n", "s.toml")}, None, "nosuch"),
    ("nurse", "/patient/admit", {"patient_id": ""}, None, "not admitted"),
    ("nurse", "/patient/admit", {"patient_id": "p1", "braden": "abc"}, None, "Braden"),
    ("nurse", "/patient/admit", {"patient_id": "p1", "braden": "99"}, None, "Braden"),
    ("nurse", "/patient/admit", {"patient_id": "p1", "bed_exit_after_min": "nan"}, None, "not admitted"),
    ("nurse", "/patient/admit", {"patient_id": "p1", "bed_exit_after_min": "inf"}, None, "not admitted"),
    ("nurse", "/patient/admit", {"patient_id": "p1", "bed_exit_after_min": "-5"}, None, "not admitted"),
    ("nurse", "/patient/admit", {"patient_id": "x" * 10000}, None, "not admitted"),
    ("admin", "/accounts", {"name": "", "password": "x", "role": "nurse"}, None, "name"),
    ("admin", "/accounts", {"name": "a b", "password": "correct horse battery", "role": "nurse"}, None, "name"),
    ("admin", "/accounts", {"name": "ok.name", "password": "correct horse battery", "role": "god"}, None, "role"),
    ("admin", "/accounts", {"name": "x" * 500, "password": "correct horse battery", "role": "nurse"}, None, "name"),
    ("admin", "/accounts/nosuch/role", {"role": "nurse"}, None, "nosuch"),
    ("admin", "/accounts/nurse.test/role", {"role": "god"}, None, "role"),
    ("admin", "/accounts/nurse.test/password", {"password": "x"}, None, "password"),
    ("admin", "/accounts/nosuch/remove", {}, None, "nosuch"),
    ("engineer", "/engineering/acquire", {"averages": "0"}, None, "averages"),
    ("engineer", "/engineering/acquire", {"averages": "nan"}, None, "averages"),
    ("engineer", "/engineering/acquire", {"averages": "1e400"}, None, "averages"),
    ("engineer", "/engineering/series", {"count": "2", "interval_s": "inf"}, None, "interval_s"),
    ("engineer", "/engineering/calibrate", {"kind": "x"}, None, "kind"),
    ("engineer", "/engineering/load", {"what": "calibration", "file": "../etc/passwd"}, None, "file"),
    ("engineer", "/engineering/load", {"what": "calibration", "file": "missing.json"}, None, "missing.json"),
    ("engineer", "/engineering/nosuch", {}, None, "nosuch"),
    ("engineer", "/engineering/acquire", None, {"averages": [1]}, "averages"),
    ("engineer", "/engineering/acquire", None, {"averages": 1.5}, "averages"),
    ("engineer", "/engineering/acquire", None, {"nosuch": 1}, "nosuch"),
    ("engineer", "/engineering/upload", {"file": (b"{x", "c.json")}, None, "c.json"),
    ("engineer", "/engineering/upload", {"file": (b"\xff", "c.json")}, None, "c.json"),
    ("engineer", "/engineering/upload", {"file": (b"[]", "c.json")}, None, "c.json"),
    ("engineer", "/engineering/upload", {"file": (b"NaN", "c.json")}, None, "c.json"),
    ("engineer", "/engineering/upload", {"file": (b"[monitor]\nframe_interval_s = nan\n", "c.toml")}, None,
     "frame_interval_s"),
    ("engineer", "/engineering/upload", {"file": (b"{}", "../x.json")}, None, "x.json"),
    ("engineer", "/engineering/upload", {"file": (b"MZ", "c.exe")}, None, "c.exe"),
]


@pytest.fixture(scope="module")
def screen(tmp_path_factory):
    """One bed screen and a logged-in client per role, shared by the cases (none of them changes anything)."""
    from webui_client import client_as

    from webui import create_app

    app = create_app(tmp_path_factory.mktemp("screen"), secure_cookies=False, TESTING=True, STREAM_MAX_S=1.0)
    return {role: client_as(app, role) for role in ("nurse", "engineer", "admin")}


@pytest.mark.parametrize(("role", "path", "form", "body", "named"), WEB_CASES,
                         ids=[f"{path} {form if body is None else body}"[:80] for _, path, form, body, _ in WEB_CASES])
def test_bad_web_input_is_refused_with_4xx_naming_it(screen, role, path, form, body, named):
    import html
    import io

    from webui_client import token

    client = screen[role]
    page = "/" + path.split("/")[1]
    if body is not None:
        answer = client.post(path, json=body, headers={"X-CSRF-Token": token(client, page)})
    else:
        data = {k: (io.BytesIO(v[0]), v[1]) if isinstance(v, tuple) else v for k, v in form.items()}
        answer = client.post(path, data={**data, "csrf_token": token(client, page)}, content_type="multipart/form-data")
    text = html.unescape(answer.get_data(as_text=True))
    assert 400 <= answer.status_code < 500, f"status {answer.status_code}"
    assert named in text
