"""The bed's records as HL7 v2.6 ORU^R01 messages, shaped as IHE PCD-01 (Communicate PCD Data) asks.

One message per record: an alarm change, a turn, an admission or discharge, or
a periodic observation of the peak pressure at each loaded site and the
posture. Segments::

    MSH  sending application and facility, receiving ones, ORU^R01^ORU_R01, the
         control id, version 2.6, and the IHE PCD-01 profile in MSH-21
    PID  the episode's patient id (PID-3, type MR) and name (PID-5); left out
         when no patient is admitted (the observations are still the bed's)
    OBR  the order the observations answer: PSM^Pressure-injury monitoring^99PSM
    OBX  one per observation: value type NM (pressure, mm[Hg] in UCUM), CWE
         (coded: site, posture, alarm, turn, episode) or ST (the monitor's words),
         the observation time (OBX-14), the user who acted (OBX-16) and the bed as
         the equipment (OBX-18)

The codes are local (``appliance.charting.codes``): MDC has none for
pressure-injury sites. Times are UTC with an explicit offset.
"""

from __future__ import annotations

import datetime
from dataclasses import dataclass

from appliance.alerts.wording import alarm_words
from appliance.charting import codes

VERSION = "2.6"
PCD_01_PROFILE = "IHE_PCD_001^IHE PCD^1.3.6.1.4.1.19376.1.6.1.1.1^ISO"
SEGMENT_END = "\r"
_ESCAPES = (("\\", "\\E\\"), ("|", "\\F\\"), ("^", "\\S\\"), ("&", "\\T\\"), ("~", "\\R\\"),
            ("\r", " "), ("\n", " "))


@dataclass(frozen=True)
class Parties:
    """Who sends (the bed's application and facility, the bed as the device) and who receives."""

    sending_application: str
    sending_facility: str
    receiving_application: str
    receiving_facility: str
    bed_id: str


def escape(text: str) -> str:
    """``text`` safe inside a field: HL7's delimiters as their escape sequences, line breaks as spaces.

    >>> escape("left|right^up & down~\\\\")
    'left\\\\F\\\\right\\\\S\\\\up \\\\T\\\\ down\\\\R\\\\\\\\E\\\\'
    """
    for raw, escaped in _ESCAPES:
        text = text.replace(raw, escaped)
    return text


def hl7_time(time_s: float) -> str:
    """Unix seconds as an HL7 DTM in UTC.

    >>> hl7_time(0.0)
    '19700101000000+0000'
    """
    return datetime.datetime.fromtimestamp(time_s, datetime.UTC).strftime("%Y%m%d%H%M%S+0000")


def oru_r01(record: dict, parties: Parties, control_id: str, written_s: float) -> str:
    """The ORU^R01 message of ``record``: ``{"event": Event.to_dict(), "name": ...}`` or
    ``{"observation": {"time_s", "posture", "patient", "peaks": {site: mmHg}}, "name": ...}``."""
    if "event" in record:
        body, observations = record["event"], _event_observations(record["event"])
    elif "observation" in record:
        body, observations = record["observation"], _peak_observations(record["observation"])
    else:
        raise ValueError(f"a charting record holds an event or an observation, got keys {sorted(record)}")
    if not observations:
        raise ValueError(f"nothing to chart in {body!r}")
    p = parties
    when = hl7_time(body["time_s"])
    segments = ["|".join(("MSH", "^~\\&", escape(p.sending_application), escape(p.sending_facility),
                          escape(p.receiving_application), escape(p.receiving_facility), hl7_time(written_s), "",
                          "ORU^R01^ORU_R01", escape(control_id), "P", VERSION, "", "", "AL", "NE", "", "UNICODE UTF-8",
                          "", "", PCD_01_PROFILE))]
    if body.get("patient"):
        segments.append(f"PID|||{escape(body['patient'])}^^^{escape(p.sending_facility)}^MR||"
                        f"{escape(record.get('name') or '')}")
    segments.append(f"OBR|1||{escape(control_id)}^{escape(p.sending_application)}|{_cwe(codes.SERVICE)}|||{when}")
    equipment = f"{escape(p.bed_id)}^{escape(p.sending_application)}"
    user = body.get("user")
    for n, (value_type, code, value, units) in enumerate(observations, start=1):
        segments.append("|".join(("OBX", str(n), value_type, _cwe(code), "", value, units, "", "", "", "", "F", "",
                                  "", when, "", escape(user) if user else "", "", equipment)))
    return SEGMENT_END.join(segments) + SEGMENT_END


def _cwe(code: tuple[str, str]) -> str:
    return f"{escape(code[0])}^{escape(code[1])}^{codes.SYSTEM}"


def _event_observations(event: dict) -> list[tuple[str, tuple[str, str], str, str]]:
    kind = (event["kind"], event["kind"])
    found: list[tuple[str, tuple[str, str], str, str]] = []
    if event["type"] == "alarm":
        found.append(("CWE", codes.ALARM, _cwe((event["key"] or "", alarm_words(event["key"]))), ""))
        found.append(("CWE", codes.ALARM_EVENT, _cwe(kind), ""))
        if event.get("priority"):
            found.append(("CWE", codes.ALARM_PRIORITY, _cwe((event["priority"], event["priority"])), ""))
    elif event["type"] == "turn":
        found.append(("CWE", codes.TURN, _cwe(kind), ""))
    elif event["type"] == "episode":
        found.append(("CWE", codes.EPISODE, _cwe(kind), ""))
    else:
        raise ValueError(f"only alarm, turn and episode events are charted, got type {event['type']!r}")
    if event.get("posture"):
        found.append(("CWE", codes.POSTURE, _cwe(codes.posture_value(event["posture"])), ""))
    if event.get("message"):
        found.append(("ST", codes.NOTE, escape(event["message"]), ""))
    return found


def _peak_observations(observation: dict) -> list[tuple[str, tuple[str, str], str, str]]:
    found: list[tuple[str, tuple[str, str], str, str]] = []
    if observation.get("posture"):
        found.append(("CWE", codes.POSTURE, _cwe(codes.posture_value(observation["posture"])), ""))
    units = "^".join(codes.UNIT_MMHG)
    for site, mmhg in sorted(observation["peaks"].items()):
        found.append(("NM", codes.peak_code(site), f"{mmhg:.1f}", units))
    return found


def acknowledgement(text: str) -> tuple[str, str, str]:
    """MSA-1 (AA, AE, AR, or the CA/CE/CR of enhanced mode), MSA-2 (the control id answered) and the error text
    (MSA-3, or ERR's) of an ACK; ValueError if it has no MSA segment."""
    segments = [s.split("|") for s in text.replace("\n", "\r").split("\r") if s]
    msa = next((s for s in segments if s[0] == "MSA"), None)
    if msa is None or len(msa) < 3:
        raise ValueError(f"an acknowledgement needs an MSA segment with a code and a control id, got {text[:80]!r}")
    err = next((s for s in segments if s[0] == "ERR"), None)
    detail = (msa[3] if len(msa) > 3 else "") or (" ".join(f for f in err[1:] if f) if err else "")
    return msa[1], msa[2], detail
