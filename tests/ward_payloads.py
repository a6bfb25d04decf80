"""What a bed publishes for the ward, made up for tests: alarm events and live summaries."""

from appliance.alerts.alarms import AlarmEvent
from appliance.alerts.events import as_event


def alarm(alarm_id=1, kind="raised", priority="high", time_s=None, key="pressure:sacrum"):
    return as_event(AlarmEvent(time_s=10.0 * alarm_id if time_s is None else time_s, kind=kind, alarm_id=alarm_id,
                               key=key, category="clinical", priority=priority, message="Sacrum dose over limit"))


def as_sent(event, bed_id, seq=None):
    """``event`` as a bed's ward link publishes it, for a test that publishes what no ward link would (a resend out
    of order, garbage); ``seq`` defaults to the alarm's id, so that alarms numbered in order are sent in order."""
    return {**event.to_dict(), "bed_id": bed_id, "seq": event.alarm_id if seq is None else seq}


def summary(bed_id, time_s=100.0, alarms=(), seq=0, source="hardware"):
    """A summary, holding every event up to ``seq`` (a ward link sets its own), from a monitor on ``source``."""
    return {"bed_id": bed_id, "time_s": time_s, "seq": seq, "peak_mmhg": 41.5,
            "regions": [{"zone": "sacrum", "peak_mmhg": 41.5, "dose": 0.3}], "turn": {"due_in_s": 3600.0},
            "alarms": [{"alarm_id": i, "key": "pressure:sacrum", "priority": p, "state": "active",
                        "message": "Sacrum dose over limit", "acknowledged_by": None} for i, p in alarms],
            "status": {"maps": 7, "faults": 0, "source": source}}
