"""The charting link the ``[charting.hl7]`` target describes, made at start and remade when an admin changes it.

The queue is a file beside the store, so a new target (another host or port,
charting switched off or on) takes over what the old one had not delivered:
records keep their numbers and go, in order, to the new interface engine. The
old link is stopped without waiting for its queue to empty, since the monitor
loop must not stall on an engine that does not answer.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from appliance.charting.chartqueue import ChartQueue
from appliance.charting.hl7 import Parties
from appliance.charting.link import ChartingLink
from appliance.errors import ConfigError
from appliance.service.config_sections import Hl7Settings, MonitorConfig

CHARTING_FILE = "charting-queue.db"


def charting_link(config: MonitorConfig, data_dir: Path) -> ChartingLink | None:
    """The link to ``config``'s interface engine with its queue in ``data_dir``; None when charting is off."""
    h = config.hl7
    if h is None or not h.enabled:
        return None
    queue = ChartQueue(Path(data_dir) / CHARTING_FILE)
    try:
        return ChartingLink(h.host, h.port, Parties(h.sending_application, h.sending_facility,
                                                    h.receiving_application, h.receiving_facility, config.bed_id),
                            queue, ack_timeout_s=h.ack_timeout_s, undelivered_alarm_s=h.undelivered_alarm_s,
                            observation_interval_s=h.observation_interval_s)
    except BaseException:
        queue.close()
        raise


def hl7_values(hl7: Hl7Settings | None) -> dict:
    """The target as the ``[charting.hl7]`` table holds it ({} when there is none)."""
    return {} if hl7 is None else dataclasses.asdict(hl7)


def describe_target(hl7: Hl7Settings | None) -> str:
    """``engine.hospital:2575``, ``engine.hospital:2575 (off)``, or ``none``."""
    if hl7 is None:
        return "none"
    return f"{hl7.host}:{hl7.port}" + ("" if hl7.enabled else " (off)")


def follow_patient(link: ChartingLink, daemon) -> None:
    """Let ``link`` name ``daemon``'s admitted patient in its messages."""
    link.patient = lambda: daemon.pipeline.episode


def retarget(daemon, config: MonitorConfig) -> None:
    """Replace ``daemon``'s charting link with the one ``config`` describes."""
    if daemon.config.data_dir is None:
        raise ConfigError("the monitor has no data folder to keep a charting queue in")
    old = next((n for n in daemon.notifiers if isinstance(n, ChartingLink)), None)
    if old is not None:
        old.close(timeout_s=0.0)
        daemon.notifiers.remove(old)
    new = charting_link(config, daemon.config.data_dir)
    if new is not None:
        follow_patient(new, daemon)
        daemon.notifiers.append(new)
