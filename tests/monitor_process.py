"""The real monitor process on the virtual bed, as the crash and fault tests run it."""

import subprocess
import sys

from appliance.store import Store

MINUTE = 60.0
ADMISSION = {"patient_id": "MRN-0042", "name": "A. Patient", "braden": 13, "bed_exit_alert": True}


def command(data_dir, model_cache, speed, scenario="supine-unturned"):
    """``appliance run`` on ``data_dir``: one map per simulated minute, ``speed`` simulated seconds a second."""
    return [sys.executable, "-m", "appliance", "run", "--scenario", scenario, "--interval", str(MINUTE),
            "--speed", str(speed), "--data-dir", str(data_dir), "--cache-dir", str(model_cache)]


def admit(data_dir):
    """A nurse admits the patient before the monitor starts: the command waits in the store for its first
    frame."""
    data_dir.mkdir(parents=True, exist_ok=True)
    with Store.open(data_dir / "appliance.db") as store:
        store.queue_command("admit", ADMISSION, "nurse.jones")


def start_monitoring(args, **popen):
    """The monitor started with ``args``, returned once it has printed its first map (that frame committed)."""
    process = subprocess.Popen(args, stdout=subprocess.PIPE, text=True, **{"stderr": subprocess.DEVNULL, **popen})
    while not process.stdout.readline()[:1].isdigit():
        assert process.poll() is None, "the monitor ended before its first map"
    return process
