"""The observation codes the bed charts under, in a local coding system.

IHE PCD codes device observations in ISO/IEEE 11073 MDC (nomenclature 10101),
which has no terms for pressure-injury sites, repositioning or a monitor's
episodes. So every code here is local, in the coding system ``99PSM``: HL7
table 0396 reserves names starting "99" for locally defined systems, and an
interface engine maps them to its own terms. Pressures are in UCUM ``mm[Hg]``.
"""

from __future__ import annotations

from appliance.alerts.anatomy import POSTURE_WORDS, site_words

SYSTEM = "99PSM"
"""The local coding system's name in HL7 v2 (CWE-3)."""

FHIR_SYSTEM = "urn:appliance:codes:99PSM"
"""The same local system as a FHIR ``Coding.system`` (a URI; no registry names these codes)."""

PATIENT_ID_SYSTEM = "urn:appliance:patient-id"
"""The identifier system of the hospital's patient id (MRN) the nurse entered at admission."""

UNIT_MMHG = ("mm[Hg]", "millimetre of mercury", "UCUM")

SERVICE = ("PSM", "Pressure-injury monitoring")
"""The order the observations belong to (OBR-4)."""

POSTURE = ("POSTURE", "Patient posture on the mat")
TURN = ("TURN", "Repositioning")
ALARM = ("ALARM", "Alarm condition")
ALARM_PRIORITY = ("ALARM-PRIORITY", "Alarm priority")
ALARM_EVENT = ("ALARM-EVENT", "Alarm change")
EPISODE = ("EPISODE", "Monitoring episode")
NOTE = ("NOTE", "The monitor's words for the change")


def peak_code(site: str) -> tuple[str, str]:
    """The code of the peak interface pressure at ``site``: ``PEAK.<site>``."""
    return f"PEAK.{site}", f"Peak interface pressure, {site_words(site)}"


def posture_value(posture: str) -> tuple[str, str]:
    """A posture as a coded value: its name and its words."""
    return posture, POSTURE_WORDS.get(posture, posture)
