"""Charting over HL7 v2 and MLLP: the messages hl7apy reads as ORU^R01 v2.6, sent to a real MLLP listener on
loopback that acknowledges, refuses, stays silent or is down, and a queue that outlives the sender."""

from __future__ import annotations

import contextlib
import socket
import threading
import time

import pytest
from hl7apy.consts import VALIDATION_LEVEL
from hl7apy.parser import parse_message

from appliance.alerts.events import Event
from appliance.charting.chartqueue import ChartQueue
from appliance.charting.hl7 import Parties, acknowledgement, oru_r01
from appliance.charting.link import ChartingLink
from appliance.charting.mllp import END, START
from appliance.core.named_layouts import get_layout
from appliance.core.protocols import default_protocol
from appliance.errors import ConfigError
from appliance.service.config import config_from_mapping
from appliance.service.daemon import MonitorDaemon
from appliance.service.virtual_bed import VirtualBedSource
from appliance.sim.loads import square_load_scene
from appliance.store import Store

PARTIES = Parties("APPLIANCE", "WARD3", "EHR", "HOSPITAL", "ward3-bed12")
T0 = 1_780_000_000.0


class Episode:
    patient_id, name = "MRN-0042", "Ada Lovelace"


class Engine:
    """An interface engine on loopback: ``answer(message, count)`` gives MSA-1 for the ``count``-th frame with
    that control id (1 the first time), or None to stay silent."""

    def __init__(self, answer=lambda message, count: "AA", port: int = 0):
        self.answer, self.received = answer, []
        self.server = socket.create_server(("127.0.0.1", port))
        self.port = self.server.getsockname()[1]
        self.connections: list[socket.socket] = []
        self._closing = False
        self._thread = threading.Thread(target=self._accept, daemon=True)
        self._thread.start()

    def control_ids(self) -> list[str]:
        return [control_id(m) for m in self.received]

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self.server.accept()
            except OSError:
                return
            self.connections.append(conn)
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        buffer = b""
        while True:
            try:
                data = conn.recv(65536)
            except OSError:
                return
            if not data:
                return
            buffer += data
            while END in buffer:
                raw, buffer = buffer.split(END, 1)
                assert raw.startswith(START)
                message = raw[1:].decode()
                self.received.append(message)
                code = self.answer(message, self.control_ids().count(control_id(message)))
                if code is not None:
                    ack = f"MSH|^~\\&|EHR|HOSPITAL|APPLIANCE|WARD3|20260101000000||ACK^R01^ACK|a{len(self.received)}|" \
                          f"P|2.6\rMSA|{code}|{control_id(message)}|{'bad patient' if code != 'AA' else ''}\r"
                    conn.sendall(START + ack.encode() + END)

    def close(self) -> None:
        for sock in (self.server, *self.connections):
            with contextlib.suppress(OSError):          # the sender may have closed it first
                sock.shutdown(socket.SHUT_RDWR)         # wakes the threads in accept() and recv()
            sock.close()
        self._thread.join()


def control_id(message: str) -> str:
    return message.split("\r")[0].split("|")[9]


def until(predicate, timeout_s: float = 20.0) -> None:
    """Wait for ``predicate`` (a bound on a hang, not a measure: nothing is asserted about the time taken)."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "the condition never came"
        time.sleep(0.02)


def events(n: int) -> list[Event]:
    return [Event(T0 + i, "turn", "repositioned", posture="left-30", message=f"turn {i}", patient="MRN-0042")
            for i in range(n)]


def link(tmp_path, port: int, **kwargs) -> ChartingLink:
    made = ChartingLink("127.0.0.1", port, PARTIES, ChartQueue(tmp_path / "charting-queue.db"),
                        **{"ack_timeout_s": 0.5, "backoff_s": 0.05, "max_backoff_s": 0.2, **kwargs})
    made.patient = Episode
    return made


def free_port() -> int:
    with socket.create_server(("127.0.0.1", 0)) as s:
        return s.getsockname()[1]


def parse(message: str):
    parsed = parse_message(message, validation_level=VALIDATION_LEVEL.STRICT, find_groups=True)
    assert parsed.name == "ORU_R01" and parsed.msh.msh_12.to_er7() == "2.6"
    assert parsed.validate()
    return parsed


# The message.

def test_alarm_message_names_patient_alarm_and_bed_and_is_valid_oru_r01():
    event = Event(T0, "alarm", "acknowledged", "medium", "clinical", "pressure:heel-left:3", "heel-left", "supine",
                  alarm_id=7, message="Pressure at the left heel | 40 min", user="nurse^kim", patient="MRN-0042")
    text = oru_r01({"event": event.to_dict(), "name": "Ada Lovelace"}, PARTIES, "ward3-bed12-5", T0 + 1)
    parse(text)
    segments = [s.split("|") for s in text.split("\r") if s]
    assert [s[0] for s in segments] == ["MSH", "PID", "OBR"] + ["OBX"] * 5
    assert segments[0][9] == "ward3-bed12-5" and segments[0][3] == "WARD3" and segments[0][2] == "APPLIANCE"
    assert segments[1][3] == "MRN-0042^^^WARD3^MR" and segments[1][5] == "Ada Lovelace"
    obx = {s[3].split("^")[0]: s for s in segments[3:]}
    assert obx["ALARM"][5] == "pressure:heel-left:3^Pressure at the left heel^99PSM"
    assert obx["ALARM-EVENT"][5].startswith("acknowledged^")
    assert obx["NOTE"][2] == "ST" and obx["NOTE"][5] == "Pressure at the left heel \\F\\ 40 min"
    assert {s[16] for s in segments[3:]} == {"nurse\\S\\kim"}
    assert {s[18] for s in segments[3:]} == {"ward3-bed12^APPLIANCE"}
    assert {s[14] for s in segments[3:]} == {"20260528202640+0000"}


def test_observation_message_carries_peaks_in_ucum_mmhg_with_local_site_codes():
    text = oru_r01({"observation": {"time_s": T0, "posture": "supine", "patient": None,
                                    "peaks": {"sacrum": 51.26, "heel-right": 33.0}}, "name": None},
                   PARTIES, "ward3-bed12-9", T0)
    parse(text)
    obx = [s.split("|") for s in text.split("\r") if s.startswith("OBX")]
    assert not any(s.startswith("PID") for s in text.split("\r"))           # no patient admitted
    mmhg = "mm[Hg]^millimetre of mercury^UCUM"
    assert [(s[2], s[3], s[5], s[6]) for s in obx] == [
        ("CWE", "POSTURE^Patient posture on the mat^99PSM", "supine^on the back^99PSM", ""),
        ("NM", "PEAK.heel-right^Peak interface pressure, right heel^99PSM", "33.0", mmhg),
        ("NM", "PEAK.sacrum^Peak interface pressure, sacrum^99PSM", "51.3", mmhg)]


def test_a_record_with_nothing_to_chart_is_refused_by_name():
    with pytest.raises(ValueError, match="event or an observation"):
        oru_r01({"thing": {}}, PARTIES, "x", T0)
    with pytest.raises(ValueError, match="type 'clock'"):
        oru_r01({"event": Event(T0, "clock", "clock-step").to_dict()}, PARTIES, "x", T0)


def test_acknowledgement_reads_code_control_id_and_error():
    assert acknowledgement("MSH|^~\\&|E\rMSA|AE|b-3|unknown patient\r") == ("AE", "b-3", "unknown patient")
    with pytest.raises(ValueError, match="MSA"):
        acknowledgement("MSH|^~\\&|E\r")


# Delivery.

def test_every_message_is_delivered_once_in_order_and_parses(tmp_path):
    engine = Engine()
    try:
        with link(tmp_path, engine.port) as sender:
            for event in events(5):
                assert sender.notify(event)
            sender.summarise({"time_s": T0 + 10, "posture": "supine", "patient": {"patient_id": "MRN-0042",
                                                                                   "name": "Ada Lovelace"},
                              "regions": [{"zone": "sacrum", "peak_mmhg": 40.0}, {"zone": "sacrum", "peak_mmhg": 44.5},
                                          {"zone": None, "peak_mmhg": 90.0}]})
            sender.summarise({"time_s": T0 + 20, "regions": [{"zone": "sacrum", "peak_mmhg": 41.0}]})  # not due
            until(lambda: sender.delivered == 6)
        assert engine.control_ids() == [f"ward3-bed12-{n}" for n in range(1, 7)]
        for message in engine.received:
            assert "PID|||MRN-0042^^^WARD3^MR||Ada Lovelace" in message
            parse(message)
        assert "PEAK.sacrum^Peak interface pressure, sacrum^99PSM||44.5|" in engine.received[-1]
    finally:
        engine.close()


def test_a_refusal_is_kept_with_the_engines_words_and_the_rest_still_go(tmp_path):
    engine = Engine(lambda message, count: "AE" if "turn 1" in message else "AA")
    try:
        with link(tmp_path, engine.port) as sender:
            for event in events(3):
                sender.notify(event)
            until(lambda: sender.delivered == 2)
            assert sender.refusals == 1
            refused = sender.queue.refused()
            assert [(r.seq, r.record["event"]["message"], r.answer) for r in refused] == [
                (2, "turn 1", "AE bad patient")]
        assert engine.control_ids() == ["ward3-bed12-1", "ward3-bed12-2", "ward3-bed12-3"]   # not sent again
    finally:
        engine.close()


def test_no_answer_is_resent_until_acknowledged(tmp_path):
    engine = Engine(lambda message, count: None if count < 3 else "AA")
    try:
        with link(tmp_path, engine.port) as sender:
            sender.notify(events(1)[0])
            until(lambda: sender.delivered == 1)
            assert sender.sent == 3
        assert engine.control_ids() == ["ward3-bed12-1"] * 3      # the same message, the same control id
    finally:
        engine.close()


def test_an_engine_down_raises_the_technical_alarm_and_gets_everything_when_it_comes_up(tmp_path):
    port = free_port()
    with link(tmp_path, port, undelivered_alarm_s=0.3) as sender:
        for event in events(3):
            sender.notify(event)
        until(lambda: "technical:charting" in sender.conditions())
        assert "ConnectionRefusedError" in sender.conditions()["technical:charting"]
        engine = Engine(port=port)
        try:
            until(lambda: sender.delivered == 3)
            until(lambda: sender.conditions() == {})
        finally:
            engine.close()
    assert engine.control_ids() == ["ward3-bed12-1", "ward3-bed12-2", "ward3-bed12-3"]


def test_queued_messages_survive_a_restart_of_the_sender_and_go_once_in_order(tmp_path):
    port = free_port()
    first = link(tmp_path, port)
    for event in events(4):
        first.notify(event)
    first.close(timeout_s=0.1)                     # the engine is down: all four stay queued
    engine = Engine(port=port)
    try:
        with link(tmp_path, port) as second:
            second.notify(events(4)[3])            # the last frame notified again after the restart: no copy
            second.notify(events(5)[4])
            until(lambda: second.delivered == 5)
        assert engine.control_ids() == [f"ward3-bed12-{n}" for n in range(1, 6)]
        assert [m.split("OBX|")[-1].split("|")[4] for m in engine.received] == [f"turn {i}" for i in range(5)]
    finally:
        engine.close()


# Configuration.

def test_charting_configuration_is_read_and_checked():
    config = config_from_mapping({"charting": {"hl7": {"host": "engine", "port": 2575, "sending_facility": "WARD3",
                                                       "receiving_application": "EHR"}}})
    assert config.hl7 is not None and (config.hl7.host, config.hl7.port, config.hl7.sending_application,
                                       config.hl7.receiving_facility) == ("engine", 2575, "APPLIANCE", "")
    assert config_from_mapping({}).hl7 is None
    good = {"host": "engine", "port": 2575, "sending_facility": "WARD3", "receiving_application": "EHR"}
    for table, problem in (({**good, "colour": 1}, "unknown key 'colour'"),
                           ({k: v for k, v in good.items() if k != "port"}, "missing 'port'"),
                           ({**good, "port": 70000}, "port must be from 1 to 65535"),
                           ({**good, "sending_facility": "W|3"}, "sending_facility must not hold"),
                           ({**good, "undelivered_alarm_s": 1}, "undelivered_alarm_s must be from 10")):
        with pytest.raises(ConfigError, match=problem):
            config_from_mapping({"charting": {"hl7": table}})
    with pytest.raises(ConfigError, match=r"\[charting\]: unknown key 'fhir'"):
        config_from_mapping({"charting": {"fhir": {}}})


# In the monitor.

def test_the_daemon_charts_its_events_and_peak_pressures_without_waiting(small_mat_calibration, tmp_path):
    model, calibration = small_mat_calibration
    grid = get_layout("grid-4x4")
    source = VirtualBedSource(grid, square_load_scene(100, 100, 30, 70, 40, 6.0), default_protocol(grid),
                              frame_interval_s=600.0)
    config = config_from_mapping({"monitor": {"layout": "grid-4x4", "frame_interval_s": 600.0},
                                  "alerts": {"alarm_dose": 0.05}})
    engine = Engine()
    charting = link(tmp_path, engine.port, observation_interval_s=1200.0)
    told: list[Event] = []
    daemon = MonitorDaemon(config, source, model, calibration, Store.open(tmp_path / "appliance.db"),
                           notifiers=[charting], on_event=told.append, say=lambda text: None)
    daemon.start()
    try:
        daemon.run(6)
        until(lambda: not charting.queue.pending())
    finally:
        daemon.close()
        engine.close()
    charted = [m for m in engine.received if "PEAK." in m]
    assert len(charted) == 3                                    # one per 1200 s of 6 frames 600 s apart
    events_charted = [m for m in engine.received if "PEAK." not in m]
    assert len(events_charted) == len([e for e in told if e.type != "clock"]) > 0
    assert any("ALARM^Alarm condition^99PSM||pressure:" in m for m in events_charted)
    for message in engine.received:
        parse(message)
