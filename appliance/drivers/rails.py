"""The analogue parts' supplies as data, and the current source's compliance derived from them.

A current source can drive an electrode only as far as its op-amp's rails allow, and the electrode's
voltage then reaches the multiplexers or switches that route it, which pass a signal only between their own
rails (beyond them their protection diodes conduct). So a profile gives each group of analogue parts its
rails (``[board.supply]``: volts, negative then positive), and :func:`check_supplies` refuses a part on
rails it is not specified for and a source that can drive an electrode further than its multiplexers pass.
The chain's compliance is the source's: what its rails allow less its headroom, or the lower
``[board.excitation] compliance_v`` a designer states (a clamp). Signals are taken centred between the
rails (a dual supply, or a single one with the signal biased at mid-supply), so a part passes a peak of
half its span.

Facts, from the data sheets as read (Analog Devices; first pages and specification tables):

* ADG725 / ADG731 (Rev. A): "1.8 V to 5.5 V single supply", "+/-2.5 V dual-supply operation", "rail-to-rail
  operation", 4 ohm on resistance: VDD - VSS from 1.8 to 5.5 V, signals from VSS to VDD. The absolute
  maximum table was not read.
* ADG1414 (Rev. A): "9.5 ohm on resistance at 25 degC and +/-15 V dual supply", "fully specified at +/-15 V,
  +12 V, +/-5 V", "rail-to-rail operation", "the input signal range extends to the supplies": VDD - VSS
  from 10 to 30 V here (the specified supplies).
* AD8251 (Rev. B): "wide supply: +/-5 V to +/-15 V"; its inputs take 13 V beyond either rail through their
  2.2 kohm resistors (Input Protection).
* AD9833: 2.3 V to 5.5 V supply; its VOUT is about 0.6 V peak to peak on about 0.3 V (not re-read: the
  research notes' recall), which the MCP4017 and the Howland source scale to the drive current, so the DDS
  never limits compliance.

>>> from appliance.drivers.profile import board_profile
>>> profile = board_profile({"profile": "reference"})
>>> round(profile.excitation.compliance_v, 3), multiplexer_peak_v(profile)
(1.556, 2.5)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from appliance.errors import AnalogueMismatch


@dataclass(frozen=True)
class SupplyRating:
    """The supply span (VDD - VSS) a part is specified over, and where that is stated."""

    part: str
    role: str
    span_v: tuple[float, float]
    source: str


RATINGS = {
    "adg725": SupplyRating("ADG725", "multiplexers", (1.8, 5.5), "ADG725/ADG731 data sheet Rev. A, features"),
    "adg731": SupplyRating("ADG731", "multiplexers", (1.8, 5.5), "ADG725/ADG731 data sheet Rev. A, features"),
    "adg1414": SupplyRating("ADG1414", "drive switches", (10.0, 30.0),
                            "ADG1414 data sheet Rev. A: fully specified at +/-5 V, +12 V, +/-15 V"),
    "ad8251": SupplyRating("AD8251", "amplifiers", (10.0, 30.0), "AD8251 data sheet Rev. B: +/-5 V to +/-15 V"),
    "ad9833": SupplyRating("AD9833", "sine source", (2.3, 5.5), "AD9833 data sheet, supply (research notes)"),
}
"""Specified supply spans by part; the multiplexer keys are the profile's ``multiplexer`` names."""
AD9833_OUTPUT_VPP = 0.6
"""The DDS's sine, volts peak to peak (research notes, recall): far below any rail here."""
AMPLIFIER_PART = {"rms": "ad8251", "ad5933": "ad8251", "parallel": None}
"""The programmable-gain in-amp on each chain's amplifier rails (the parallel chain's in-amps are fixed-gain)."""


def half_span_v(rails: tuple[float, float]) -> float:
    """The peak a part on ``rails`` (negative, positive) passes around their midpoint, volts."""
    return (rails[1] - rails[0]) / 2


def multiplexer_peak_v(profile) -> float:
    """The largest peak the profile's multiplexers (or drive switches) pass, volts."""
    return half_span_v(profile.supply.multiplexers)


def source_peak_v(supply) -> float:
    """The largest peak the current source's op-amp drives on its rails, volts."""
    return half_span_v(supply.current_source) - supply.source_headroom_v


def check_supplies(name: str, multiplexer: str, chain: str, supply, compliance_v: float | None,
                   uses_dds: bool) -> float:
    """The source's compliance (volts rms) for these rails, or :class:`AnalogueMismatch` naming every problem.

    ``compliance_v`` is the designer's stated limit, or None to take what the source's rails allow.
    """
    problems: list[str] = []
    for group, rails in (("multiplexers", supply.multiplexers), ("current_source", supply.current_source),
                         ("amplifiers", supply.amplifiers)):
        if not rails[0] <= 0 <= rails[1] or rails[0] == rails[1]:
            problems.append(f"[board.supply] {group} = {list(rails)}: rails must be (negative or 0, positive) volts")
    if problems:
        raise AnalogueMismatch(f"profile {name}:\n" + "\n".join(f"  {p}" for p in problems))
    parts = [(RATINGS[multiplexer], supply.multiplexers)]
    amplifier = AMPLIFIER_PART[chain]
    if amplifier:
        parts.append((RATINGS[amplifier], supply.amplifiers))
    for rating, rails in parts:
        span = rails[1] - rails[0]
        low, high = rating.span_v
        if not low <= span <= high:
            problems.append(f"the {rating.part} {rating.role} on {_rails(rails)} ({span:g} V between the rails) are "
                            f"outside the {low:g} to {high:g} V the part is specified for ({rating.source})")
    source_peak = source_peak_v(supply)
    if source_peak <= 0:
        problems.append(f"the current source on {_rails(supply.current_source)} with {supply.source_headroom_v:g} V "
                        "headroom cannot drive at all")
    if compliance_v is not None and compliance_v * math.sqrt(2) > source_peak:
        problems.append(f"[board.excitation] compliance_v = {compliance_v:g} V rms "
                        f"({compliance_v * math.sqrt(2):.2f} V peak) is beyond what the current source on "
                        f"{_rails(supply.current_source)} can drive ({source_peak:.2f} V peak after its "
                        f"{supply.source_headroom_v:g} V headroom)")
    peak = min(source_peak, compliance_v * math.sqrt(2)) if compliance_v is not None else source_peak
    passed = half_span_v(supply.multiplexers)
    if peak > passed:
        problems.append(f"the current source's compliance {peak / math.sqrt(2):.2f} V rms ({peak:.2f} V peak) "
                        f"exceeds what the {RATINGS[multiplexer].part} {RATINGS[multiplexer].role} pass on "
                        f"{_rails(supply.multiplexers)} ({passed:.2f} V peak, {passed / math.sqrt(2):.2f} V rms): "
                        "an open electrode would drive them beyond their rails; power the source from the "
                        "multiplexers' rails or state a compliance_v they pass")
    if uses_dds and AD9833_OUTPUT_VPP / 2 > half_span_v(supply.current_source):
        problems.append(f"the AD9833's {AD9833_OUTPUT_VPP:g} V p-p sine does not fit the current source's rails "
                        f"{_rails(supply.current_source)}")
    if problems:
        raise AnalogueMismatch(f"profile {name}: its analogue parts do not fit their supplies:\n"
                               + "\n".join(f"  {p}" for p in problems))
    return peak / math.sqrt(2)


def _rails(rails: tuple[float, float]) -> str:
    return f"{rails[0]:+g}/{rails[1]:+g} V"
