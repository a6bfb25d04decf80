"""Power cuts for the tests of the store's durability: the monitor in a process that can be killed (or have its
file system cut off) at a random moment or inside a store commit, the nurse who acknowledges its alarms as the web
screen does and notes what the store has promised, and an ext4 file system on a loop device.

Run as a script it is the monitor (``appliance run``'s arguments), patched from the environment:
``POWER_CUT_TRIGGER`` names a file whose appearance arms a strike (``POWER_CUT_MODE`` ``kill``: SIGKILL; ``cut``:
shut the data file system down without flushing, then SIGKILL) in one of the next frame commits, at a random
delay after its COMMIT statement begins (writing the WAL, then fsyncing it) of up to the median COMMIT's
duration; ``POWER_CUT_SYNC`` forces every transaction's ``synchronous`` level (the negative control).
"""

from __future__ import annotations

import fcntl
import json
import os
import random
import re
import shutil
import signal
import sqlite3
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

MINUTE = 60.0
USER = "nurse.power"
FS_SHUTDOWN = 0x8004587D        # EXT4_IOC_SHUTDOWN = XFS_IOC_GOINGDOWN = _IOR('X', 125, __u32)
NO_LOG_FLUSH = 2                # EXT4_GOING_FLAGS_NOLOGFLUSH: drop the page cache and the journal's tail
# The data partition's options: noatime, since the screen reads the store all day and atime would turn each read
# into a metadata write on the SD card; data=ordered (ext4's default, named so nobody drops it for writeback) so a
# file's new blocks reach the card before the journal points at them; barriers stay on (the default), as every
# fsync of the store relies on the card's cache being flushed.
MOUNT_OPTIONS = "noatime,data=ordered"

# Turned every 30 min (left, back, right, back) for two days: with the alarm dose at 0.05 of the tolerance and a
# 15-min turn interval each half hour raises a turn reminder and pressure alarms at new sites to acknowledge.
CONFIG = """\
[alerts]
alarm_dose = 0.05
turn_interval_min = 15
escalate_after_min = 5

[store]
history_interval_s = 60
"""


def scenario(turn_every_s: float = 1800.0, duration_s: float = 172800.0) -> str:
    """A scenario file's text: lie down supine, then turn every ``turn_every_s``."""
    postures = ("left-30", "supine", "right-30", "supine")
    events = ['[[event]]\nat_s = 0\nkind = "lie-down"\nposture = "supine"\n']
    for i, at in enumerate(range(int(turn_every_s), int(duration_s), int(turn_every_s))):
        events.append(f'[[event]]\nat_s = {at}\nkind = "turn"\nposture = "{postures[i % 4]}"\ntransition_s = 20\n')
    return (f'[scene]\ndescription = "turned every {turn_every_s / 60:g} min"\nweight_kg = 75\nheight_cm = 175\n'
            f"duration_s = {duration_s:g}\n\n" + "\n".join(events))


def monitor_command(work: Path, data_dir: Path, model_cache: Path) -> list[str]:
    """The monitor on the fast-turning patient, as fast as it goes, one simulated minute a frame."""
    (work / "power-cut.toml").write_text(CONFIG)
    (work / "turned-30min.toml").write_text(scenario())
    return [sys.executable, __file__, "run", "--config", str(work / "power-cut.toml"),
            "--scenario", str(work / "turned-30min.toml"), "--interval", str(MINUTE), "--speed", "0",
            "--data-dir", str(data_dir), "--cache-dir", str(model_cache)]


class Life:
    """One run of the monitor until it is struck; its stdout and stderr go to files outside the data."""

    def __init__(self, command: list[str], work: Path, n: int, mode: str | None = None,
                 synchronous: str | None = None):
        self.out, self.err = work / f"life-{n}.out", work / f"life-{n}.err"
        self.trigger = work / f"life-{n}.arm"
        env = dict(os.environ)
        if mode:
            env.update(POWER_CUT_MODE=mode, POWER_CUT_TRIGGER=str(self.trigger), POWER_CUT_SEED=str(n))
        if synchronous:
            env["POWER_CUT_SYNC"] = synchronous
        with open(self.out, "w") as out, open(self.err, "w") as err:
            self.process = subprocess.Popen(command, stdout=out, stderr=err, env=env)

    def arm(self) -> None:
        """Strike inside one of the next frame commits."""
        self.trigger.touch()

    def kill(self) -> None:
        if self.process.poll() is None:
            os.kill(self.process.pid, signal.SIGKILL)
        self.process.wait(timeout=30)

    def resumed_from(self) -> float | None:
        found = re.search(r"resumed from the store at ([0-9.]+) s", self.err.read_text())
        return None if found is None else float(found.group(1))

    def armed(self) -> tuple[float, bool] | None:
        """The frame time of the commit the strike was armed in, and whether the process died inside its COMMIT
        statement (it began, and never returned)."""
        text = self.out.read_text()
        found = re.search(r"^armed in the commit of ([0-9.]+) ", text, re.M)
        if found is None:
            return None
        t = found.group(1)
        return float(t), f"COMMIT {t}\n" in text and f"committed {t}\n" not in text


class Nurse:
    """Acknowledges every open alarm the way the web screen does (a command queued through ``Store``) and keeps
    what the store has shown committed, which must survive any crash or cut after it was seen.

    A reader sees a ``synchronous=FULL`` commit only once its WAL frames are fsynced, so what it reads is promised;
    the pressure history is committed NORMAL and only promised up to the frame whose FULL commit follows it, so
    rows are taken up to the alert state's time. The nurse looks through a read-only connection: ``Store.close``
    checkpoints the WAL (with an fsync), which would make everything durable and hide the monitor's own settings.
    """

    def __init__(self, db_path: Path):
        self.db_path = db_path
        self.queued: dict[int, int] = {}                    # command id -> alarm id
        self.commands: dict[int, tuple] = {}                # command id -> (state, result), once done or refused
        self.acknowledged: set[tuple] = set()               # (alarm id, user, time)
        self.doses: dict[tuple, float | None] = {}          # (time, region id) -> dose, from the history
        self.last_time_s: float | None = None
        self.dose_state = None

    def round(self) -> bool:
        """One look at the store and one acknowledgement per open alarm; False if the store cannot be read."""
        from appliance.errors import StoreError
        from appliance.store import Store

        try:
            seen = self._look()
            if seen is None:
                return True
            for alarm_id in seen - set(self.queued.values()):
                with Store.open(self.db_path) as store:
                    self.queued[store.queue_command("acknowledge", {"alarm_id": alarm_id}, USER)] = alarm_id
            return True
        except (sqlite3.Error, OSError, StoreError):          # the file system is gone: the power is off
            return False

    def _look(self) -> set[int] | None:
        """Note what is committed, in one read transaction; returns the open alarms nobody acknowledged."""
        if not self.db_path.exists():
            return None
        db = sqlite3.connect(f"file:{self.db_path}?mode=ro", uri=True, isolation_level=None)
        try:
            db.execute("BEGIN")
            row = db.execute("SELECT value FROM state WHERE name = 'alerts'").fetchone()
            if row is None:
                return None
            state = json.loads(row[0])
            t0 = -1.0 if self.last_time_s is None else self.last_time_s
            self.doses.update(((t, i), d) for t, i, d in db.execute(
                "SELECT time_s, region_id, dose FROM region_history WHERE time_s > ? AND time_s <= ?",
                (t0, state["last_time_s"])))
            self.last_time_s, self.dose_state = state["last_time_s"], state["dose"]["cells"]["dose"]
            self.acknowledged |= set(db.execute("SELECT alarm_id, user, time_s FROM events"
                                                " WHERE kind = 'acknowledged'"))
            self.commands.update((i, (s, r)) for i, s, r in db.execute(
                "SELECT id, state, result FROM commands WHERE state != 'pending'") if i in self.queued)
            db.execute("COMMIT")
        finally:
            db.close()
        return {a["alarm_id"] for a in state["alarms"]["alarms"] if a["acknowledged_by"] is None}

    def done(self) -> int:
        return sum(state == "done" for state, _ in self.commands.values())


def check_store(db_path: Path, nurse: Nurse) -> dict:
    """Open the store as the restarted monitor would: its integrity, and what the nurse saw committed that is
    missing or changed."""
    db = sqlite3.connect(db_path)
    try:
        integrity = db.execute("PRAGMA integrity_check").fetchall()
        commands = {i: (s, r) for i, s, r in db.execute("SELECT id, state, result FROM commands")}
        lost_commands = {i: c for i, c in nurse.commands.items() if commands.get(i) != c}
        acknowledged = set(db.execute("SELECT alarm_id, user, time_s FROM events WHERE kind = 'acknowledged'"))
        doses = {(t, i): d for t, i, d in db.execute("SELECT time_s, region_id, dose FROM region_history")}
        lost_doses = {k: d for k, d in nurse.doses.items() if doses.get(k, "lost") != d}
        row = db.execute("SELECT value FROM state WHERE name = 'alerts'").fetchone()
        state = json.loads(row[0]) if row else {"last_time_s": -1.0, "alarms": {"alarms": []}, "dose": {}}
    finally:
        db.close()
    acknowledged_ids = {alarm for alarm, _, _ in nurse.acknowledged}
    unacknowledged = [a["alarm_id"] for a in state["alarms"]["alarms"]
                      if a["alarm_id"] in acknowledged_ids and a["acknowledged_by"] != USER]
    same_frame = state["last_time_s"] == nurse.last_time_s
    return {"integrity": integrity, "lost_commands": lost_commands,
            "lost_acknowledgements": nurse.acknowledged - acknowledged, "lost_doses": lost_doses,
            "unacknowledged_again": unacknowledged,
            "rewound": nurse.last_time_s is not None and state["last_time_s"] < nurse.last_time_s,
            "dose_state_differs": same_frame and state["dose"].get("cells", {}).get("dose") != nurse.dose_state,
            "last_time_s": state["last_time_s"]}


def losses(report: dict) -> int:
    """How many promised things a check found missing or changed."""
    return ((report["integrity"] != [("ok",)]) + len(report["lost_commands"]) + len(report["lost_acknowledgements"])
            + len(report["lost_doses"]) + len(report["unacknowledged_again"]) + report["rewound"]
            + report["dose_state_differs"])


def cut_power(folder: Path) -> None:
    """Shut down the file system holding ``folder`` at once: what is only in the page cache never reaches the
    device, as when the power goes (xfstests' ``godown``)."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.ioctl(fd, FS_SHUTDOWN, struct.pack("I", NO_LOG_FLUSH))
    finally:
        os.close(fd)


class LoopExt4:
    """An ext4 file system in an image file on a loop device, mounted as the appliance mounts its data partition.
    ``cut`` is the power cut; ``recover`` detaches, runs e2fsck -fy as boot does, and mounts it again."""

    def __init__(self, work: Path, size_mb: int = 96, options: str = MOUNT_OPTIONS):
        self.image, self.mountpoint, self.options = work / "data.img", work / "mnt", options
        self.loop: str | None = None
        self.mountpoint.mkdir()
        with open(self.image, "wb") as f:
            f.truncate(size_mb << 20)
        _run("mkfs.ext4", "-q", "-F", "-L", "appdata", str(self.image))

    def mount(self) -> None:
        self.loop = _run("losetup", "--find", "--show", str(self.image)).strip()
        _run("mount", "-t", "ext4", "-o", self.options, self.loop, str(self.mountpoint))

    def cut(self) -> None:
        cut_power(self.mountpoint)

    def unmount(self) -> None:
        """Unmount and detach whatever is mounted or attached; safe to call twice."""
        try:
            if os.path.ismount(self.mountpoint):
                for _ in range(50):                   # a dying process may hold a file a moment longer
                    umount = subprocess.run(["umount", str(self.mountpoint)], capture_output=True, check=False)
                    if umount.returncode == 0:
                        break
                    time.sleep(0.1)
                else:
                    _run("umount", "--lazy", str(self.mountpoint))
        finally:
            if self.loop is not None:
                _run("losetup", "-d", self.loop)
                self.loop = None

    def recover(self) -> int:
        """Boot after the cut: e2fsck -fy on the device, then mount; returns e2fsck's exit status."""
        self.unmount()
        status = subprocess.run(["e2fsck", "-fy", str(self.image)], capture_output=True, text=True,
                                check=False).returncode
        self.mount()
        return status


def loop_devices_unavailable() -> str | None:
    """Why this machine cannot run the loop-device tests, or None if it can."""
    if os.geteuid() != 0:
        return "needs root for losetup and mount"
    missing = [tool for tool in ("losetup", "mkfs.ext4", "e2fsck", "mount", "umount") if shutil.which(tool) is None]
    if missing:
        return f"needs {', '.join(missing)}"
    if not os.path.exists("/dev/loop-control"):
        return "no loop devices (/dev/loop-control is missing)"
    return None


def _run(*command: str) -> str:
    return subprocess.run(command, check=True, capture_output=True, text=True).stdout


# The monitor process, patched.

def _patch_store() -> None:
    from appliance.store import database

    forced = os.environ.get("POWER_CUT_SYNC")
    if forced:
        transaction = database.Store._transaction
        database.Store._transaction = lambda self, synchronous: transaction(self, forced)
    trigger = os.environ.get("POWER_CUT_TRIGGER")
    if trigger:
        _arm_in_commits(database.Store, trigger, os.environ["POWER_CUT_MODE"],
                        random.Random(int(os.environ.get("POWER_CUT_SEED", "0"))))


def _arm_in_commits(store_class, trigger: str, mode: str, rng: random.Random) -> None:
    """Time this machine's COMMITs of frames; once ``trigger`` exists, strike inside one at a random delay up to
    their median duration, from a thread already waiting (a thread started then would come too late)."""
    commit_frame, durations, commit = store_class.commit_frame, [], {"at": 0.0, "armed": None}
    go = threading.Event()

    def at_statement(sql: str) -> None:
        if sql == "COMMIT":
            commit["at"] = time.perf_counter()
            if commit["armed"] is not None:
                print(f"COMMIT {commit['armed']}", flush=True)
                go.set()

    def striker(folder: str, delay_s: float) -> None:
        go.wait()
        while time.perf_counter() < commit["at"] + delay_s:
            pass                                            # sleep() would overshoot a sub-millisecond delay
        if mode == "cut":
            cut_power(Path(folder))
        os.kill(os.getpid(), signal.SIGKILL)

    def timed_commit_frame(self, now_s, *args, **kwargs):
        if not durations:
            self._conn().set_trace_callback(at_statement)
        elif commit["armed"] is None and os.path.exists(trigger) and rng.random() < 0.3:
            commit["armed"] = now_s
            delay_s = rng.uniform(0.0, sorted(durations)[len(durations) // 2])
            print(f"armed in the commit of {now_s} at {delay_s * 1e3:.3f} ms", flush=True)
            threading.Thread(target=striker, args=(os.path.dirname(self.path), delay_s), daemon=True).start()
        commit_frame(self, now_s, *args, **kwargs)
        durations.append(time.perf_counter() - commit["at"])
        if commit["armed"] == now_s:
            print(f"committed {now_s}", flush=True)

    store_class.commit_frame = timed_commit_frame


if __name__ == "__main__":
    _patch_store()
    from appliance.cli import main

    raise SystemExit(main(sys.argv[1:]))
