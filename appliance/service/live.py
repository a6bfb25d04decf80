"""The live channel: the newest frame's summary as a JSON file the web screen reads.

The monitor hands each frame's snapshot over and goes on; a writer thread keeps
only the newest one (a slower disk skips snapshots, never frames) and replaces
``live.json`` by rename, so a reader never sees half a file. Readers need no
connection to the monitor, and any number of them costs the loop nothing.
``sequence`` rises by one per frame and ``written_at`` is the wall clock, so a
reader can tell a stale screen (the monitor stopped) from a quiet patient.
"""

from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path

import numpy as np

from appliance.core.pressure import KPA_PER_MMHG
from appliance.supervise import Supervised

FORMAT = "appliance-live/1"


class LiveChannel:
    """Publishes snapshots to ``path`` from its own thread; ``publish`` never waits on the disk."""

    def __init__(self, path: Path, *, backoff_s: float = 0.5):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.written = self.skipped = 0
        self._pending: dict | None = None
        self._wake = threading.Condition()
        self._closing = False
        self._worker = Supervised("live-view writer", self._run, backoff_s=backoff_s)   # a failed write: retried
        self._worker.start()

    @property
    def fault(self) -> str | None:
        """The writer's last failure while it is failing (the daemon shows it as a technical alarm)."""
        return self._worker.fault

    def publish(self, snapshot: dict) -> None:
        """Hand over the newest snapshot; one not yet written is replaced (counted in ``skipped``)."""
        with self._wake:
            if self._pending is not None:
                self.skipped += 1
            self._pending = snapshot
            self._wake.notify()

    def close(self) -> None:
        """Write what is pending, then stop the writer."""
        with self._wake:
            self._closing = True
            self._wake.notify()
        self._worker.stop()
        self._worker.join()

    def _run(self) -> None:
        while True:
            with self._wake:
                while self._pending is None and not self._closing:
                    self._wake.wait()
                snapshot, self._pending = self._pending, None
                if snapshot is None:
                    return
            self._write(snapshot)

    def _write(self, snapshot: dict) -> None:
        text = json.dumps({**snapshot, "format": FORMAT, "written_at": time.time()}, separators=(",", ":"))
        tmp = self.path.with_name(f".{self.path.name}.tmp")
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, self.path)        # no fsync: a live view lost in a power cut is rewritten next frame
        self.written += 1
        self._worker.ok()


def read_live(path: Path) -> dict | None:
    """The newest snapshot, or None before the monitor wrote one."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    if data.get("format") != FORMAT:
        raise ValueError(f"{path} is not a live snapshot ({FORMAT}), format {data.get('format')!r}")
    return data


def map_mmhg(pressure_kpa: np.ndarray) -> list[list[float | None]]:
    """A map in whole tenths of mmHg for the screen, None where nothing could be read."""
    mmhg = np.round(np.asarray(pressure_kpa, dtype=float) / KPA_PER_MMHG, 1)
    shown = mmhg.astype(object)             # Python floats, element by element in C rather than in a loop here
    shown[~np.isfinite(mmhg)] = None
    return shown.tolist()
