"""Faults around the monitor rather than in the mat: a second monitor on the same folder, damaged files,
wall-clock steps, a background thread that fails and a full disk. Each is a technical alarm or a refusal
naming what is wrong; none kills the monitor with a traceback or loses a record."""

import os
import signal
import subprocess

import pytest

from appliance.errors import DataDirInUse
from appliance.service.datalock import lock_data_dir
from monitor_process import MINUTE, command, start_monitoring


# One data folder per monitor.

def test_a_second_lock_on_a_folder_is_refused_naming_it_and_the_holder(tmp_path):
    held = lock_data_dir(tmp_path)
    with pytest.raises(DataDirInUse, match=rf"data folder {tmp_path} is in use by another monitor "
                                           rf"\(pid {os.getpid()}\)"):
        lock_data_dir(tmp_path)
    held.release()
    lock_data_dir(tmp_path).release()           # released: the folder can be taken again


def test_a_second_monitor_on_a_folder_exits_2_and_one_after_a_sigkill_starts(tmp_path, bed_monitoring, model_cache):
    data = tmp_path / "data"
    first = start_monitoring(command(data, model_cache, speed=1.0))
    try:
        second = subprocess.run(command(data, model_cache, speed=0) + ["--frames", "1"], capture_output=True,
                                text=True, timeout=600)
        assert second.returncode == 2
        assert second.stderr.splitlines()[-1] == (f"appliance: error: data folder {data} is in use by another "
                                                  f"monitor (pid {first.pid}): each monitor needs a folder of "
                                                  f"its own")
        assert "Traceback" not in second.stderr
    finally:
        os.kill(first.pid, signal.SIGKILL)
        first.wait()
        first.stdout.close()
    after = subprocess.run(command(data, model_cache, speed=0) + ["--frames", "1"], capture_output=True, text=True,
                           timeout=600)
    assert after.returncode == 0, after.stderr
