"""Patient episodes: who lies in the bed, from admission to discharge.

Doses, the turn clock and reminders belong to a patient, not to the bed: a new
patient starts afresh, and the earlier patient's events stay in the store under
their identifier. A monitor with no one admitted still alarms (the patient is
then unnamed): a bed must never go quiet for want of paperwork.

The risk score is the Braden scale (6 to 23; 18 or less is at risk: Bergstrom et
al. 1987), the one most wards record. The bed-exit alert is off unless the
patient's care plan asks for it (falls risk), after ``bed_exit_after_s`` with
no one on the mat.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from appliance.errors import ConfigError

BRADEN_RANGE = (6, 23)
MAX_ID_CHARS = 64
MAX_NAME_CHARS = 100
DEFAULT_BED_EXIT_AFTER_S = 60.0
BED_EXIT_AFTER_RANGE_S = (10.0, 3600.0)


@dataclass(frozen=True)
class Episode:
    """One patient's stay in the bed: identifier (the hospital's, e.g. the MRN), optional name and Braden score,
    when and by whom admitted, and whether leaving the bed alerts."""

    patient_id: str
    admitted_s: float
    admitted_by: str
    name: str | None = None
    braden: int | None = None
    bed_exit_alert: bool = False
    bed_exit_after_s: float = DEFAULT_BED_EXIT_AFTER_S

    def __post_init__(self):
        _text("patient identifier", self.patient_id, MAX_ID_CHARS, required=True)
        _text("admitting user", self.admitted_by, MAX_NAME_CHARS, required=True)
        _text("patient name", self.name, MAX_NAME_CHARS, required=False)
        if self.braden is not None and (isinstance(self.braden, bool) or not isinstance(self.braden, int)
                                        or not BRADEN_RANGE[0] <= self.braden <= BRADEN_RANGE[1]):
            raise ConfigError(f"Braden score must be a whole number from {BRADEN_RANGE[0]} to {BRADEN_RANGE[1]}, "
                              f"got {self.braden!r}")
        if not isinstance(self.bed_exit_alert, bool):
            raise ConfigError(f"bed-exit alert must be true or false, got {self.bed_exit_alert!r}")
        low, high = BED_EXIT_AFTER_RANGE_S
        after = self.bed_exit_after_s
        if isinstance(after, bool) or not isinstance(after, (int, float)) or not math.isfinite(after) \
                or not low <= after <= high:
            raise ConfigError(f"bed-exit delay must be {low:g} to {high:g} s, got {after!r}")
        if isinstance(self.admitted_s, bool) or not isinstance(self.admitted_s, (int, float)) \
                or not math.isfinite(self.admitted_s):
            raise ConfigError(f"admission time must be a finite number of seconds, got {self.admitted_s!r}")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> Episode:
        try:
            return cls(**d)
        except TypeError as exc:
            raise ConfigError(f"episode is malformed: {exc}") from None


def _text(what: str, value, limit: int, *, required: bool) -> None:
    if value is None and not required:
        return
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(f"{what} must be non-empty text, got {value!r}")
    if len(value) > limit:
        raise ConfigError(f"{what} is {len(value)} characters long; at most {limit} are kept")
    if not value.isprintable():
        raise ConfigError(f"{what} {value!r} holds a control character")
