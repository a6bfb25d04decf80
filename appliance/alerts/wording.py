"""Alarm keys and setting values in the words a nurse reads.

Keys such as ``pressure:sacrum:3`` or ``technical:ward-link`` identify an alarm to the software and the
store; a nurse's page shows ``Pressure at the sacrum`` or ``Equipment: link to the ward station`` instead.

>>> alarm_words("pressure:heel-left:3"), alarm_words("turn:overdue:2"), alarm_words("technical:electrode:5")
('Pressure at the left heel', 'Turn overdue', 'Equipment: electrode 5')
"""

from __future__ import annotations

from appliance.alerts.anatomy import SITES, SMALL_MAT_SITE, UNIDENTIFIED_SITE, site_words

TECHNICAL_WORDS = {
    "electrode": "electrode", "front-end": "measuring electronics", "no-data": "no pressure map from the mat",
    "storage": "the monitor's storage", "saved-state": "the saved alarm state",
    "live-view": "the bedside screen's data", "notifier": "notification", "ward-link": "link to the ward station",
    "ward-confirm": "confirmations from the ward station", "ward-outbox": "messages kept for the ward station",
    "ward-link-sender": "sending to the ward station", "calibration": "pressure calibration",
    "charting": "charting to the hospital record", "charting-queue": "messages kept for the hospital record",
}
"""The part a technical alarm is about; the key's further parts (an electrode's number) follow in words."""

SETTING_WORDS = {"reswick-rogers": "Reswick and Rogers (1976)", "linder-ganz": "Linder-Ganz and others (2006)",
                 "reset": "cleared after the relief time", "decay": "falls from the first second of relief"}
"""Values of the settings' choices (tolerance curves, recovery) as their sources or in plain words."""


def alarm_words(key: str | None) -> str:
    """What the alarm with ``key`` is about, in plain words ("" for none)."""
    if not key:
        return ""
    kind, _, rest = key.partition(":")
    if kind == "pressure":
        site = rest.split(":")[0]
        named = site in SITES or site in (SMALL_MAT_SITE, UNIDENTIFIED_SITE)
        return f"Pressure at the {site_words(site) if named else site.replace('-', ' ')}"
    if kind == "turn":
        return "Turn overdue" if rest.startswith("overdue") else "Turn due"
    if kind == "bed-exit":
        return "Out of bed"
    if kind == "technical":
        part, _, detail = rest.partition(":")
        words = TECHNICAL_WORDS.get(part, part.replace("-", " "))
        return f"Equipment: {words}{' ' + detail.replace(':', ' ') if detail else ''}"
    return key.replace(":", " ").replace("-", " ").capitalize()


def setting_words(value) -> str:
    """A setting's value as the settings page shows it."""
    return SETTING_WORDS.get(value, str(value)) if isinstance(value, str) else str(value)
