"""The self-test a clinical engineer runs: each chip answers, the signal path works, every electrode touches.

Chips with registers are read back (:meth:`FrontEnd.self_check`). Write-only parts
(the DDS, the multiplexers, the AD8251) are checked through the signal they
shape: no signal with the source off, a signal with it on, the same reading at
two gains (on the parallel chain: the AD7606's two ranges, and every converter
answering with the source off), and a converter that does not repeat one code.
The contact table comes last.
"""

from __future__ import annotations

from dataclasses import dataclass

from appliance.drivers.contact import ContactReport, check_contacts
from appliance.drivers.frontend import OVER_RANGE, ChipCheck, FrontEnd
from appliance.errors import ApplianceError

QUIET_FRACTION = 0.05        # with the source off, the most sensitive range must read below this
GAIN_AGREEMENT = 0.02        # one reading at two gains must agree to this, relative
SIGNAL_OVER_ACCURACY = 10    # parallel chain: the test reading must be this many times the stated absolute accuracy


@dataclass(frozen=True)
class SelfTestReport:
    checks: tuple[ChipCheck, ...]
    contact: ContactReport | None

    @property
    def passed(self) -> bool:
        return all(c.ok for c in self.checks) and self.contact is not None and not self.contact.open_electrodes

    def text(self) -> str:
        width = max(len(c.part) for c in self.checks)
        lines = [f"{'ok ' if c.ok else 'FAIL'}  {c.part:<{width}}  {c.where:<14}  {c.detail}" for c in self.checks]
        lines.append("")
        lines.append(self.contact.table() if self.contact else "contact check: not run (see failures above)")
        lines.append("")
        lines.append("self-test passed" if self.passed else "self-test FAILED")
        return "\n".join(lines)


def run_self_test(front_end: FrontEnd, n_electrodes: int) -> SelfTestReport:
    """Chip read-backs, the signal path on electrodes 1-2, then the contact check of every electrode."""
    front_end.check_electrodes(n_electrodes)
    checks = list(front_end.self_check())
    checks += _signal_path_parallel(front_end) if getattr(front_end, "parallel", False) else _signal_path(front_end)
    contact = None
    try:
        contact = check_contacts(front_end, n_electrodes)
    except (ApplianceError, OSError) as exc:
        checks.append(ChipCheck("contact check", "electrodes", False, str(exc)))
    return SelfTestReport(tuple(checks), contact)


def _checker(results: list):
    """``check(part, action)``: run ``action`` (giving ok, detail) and add its signal-path check to ``results``;
    a failure is reported with its message, not raised."""
    def check(part, action):
        try:
            ok, detail = action()
        except (ApplianceError, OSError) as exc:
            ok, detail = False, str(exc)
        results.append(ChipCheck(part, "signal path", ok, detail))

    return check


def _signal_path(fe: FrontEnd) -> list[ChipCheck]:
    results: list[ChipCheck] = []
    check = _checker(results)
    pair = (1, 2)
    state: dict = {}

    def quiet():
        fe.forget_routing()
        fe.mux.select(pair, pair)
        fe.set_range(len(fe.ranges) - 1)
        fe.clock.sleep(fe.settle_s(True, True, None, None))
        state["off"] = fe.sample_source_off()
        fraction = state["off"].fraction
        return fraction < QUIET_FRACTION, (f"source off reads {fraction:.1%} of the most sensitive range"
                                           + ("" if fraction < QUIET_FRACTION else ": enable line stuck on, "
                                              "or interference"))

    def signal():
        fe.start_excitation()
        fe.contact_current()
        measured = fe.measure(pair, pair)
        state["on"] = measured
        ok = not measured.saturated and measured.sample.fraction > QUIET_FRACTION \
            and measured.sample.raw != state["off"].raw
        detail = (f"source on reads {abs(measured.sample.volts) * 1e3:.3f} mV on electrodes 1-2 "
                  f"({fe.ranges[measured.range_index].label})")
        if measured.sample.raw == state["off"].raw:
            detail += f"; the converter returned code {measured.sample.raw} with the source off and on: stuck"
        elif not ok:
            detail += ": no usable signal (sine source, current source or multiplexers)"
        return ok, detail

    def gains():
        r = state["on"].range_index
        other = r - 1 if r > 0 else r + 1
        if not 0 <= other < len(fe.ranges):
            return True, "only one range"
        first = fe.measure(pair, pair, range_index=r).sample
        second = fe.measure(pair, pair, range_index=other).sample
        if fe.ranges[other].gain == fe.ranges[r].gain:
            return True, "adjacent ranges share the amplifier gain"
        ratio = second.volts / first.volts
        ok = abs(ratio - 1) < GAIN_AGREEMENT
        return ok, (f"x{fe.ranges[r].gain:g} and x{fe.ranges[other].gain:g} agree to {abs(ratio - 1):.2%}"
                    + ("" if ok else ": programmable gain wrong"))

    try:
        check("current source and sine off", quiet)
        check("sine, current source and multiplexers", signal)
        if results[-1].ok:
            check("AD8251 gain steps", gains)
    finally:
        fe.stop_excitation()
    return results


def _signal_path_parallel(fe) -> list[ChipCheck]:
    """The parallel chain on electrodes 1-2: every converter quiet with the source off, then the pair's own
    channel at the contact current, at both ranges."""
    results: list[ChipCheck] = []
    check = _checker(results)
    pair = (1, 2)
    channel = fe.cmap.channel_of(*pair)[0]
    state: dict = {}

    def quiet():
        fe.measure_zero()
        sample = fe.step(pair, list(range(fe.cmap.n_channels)), len(fe.ranges) - 1)
        state["off"] = sample
        worst = float(sample.fraction.max())
        return worst < QUIET_FRACTION, (f"{fe.cmap.n_adcs} converters answer; source off, the largest channel reads "
                                        f"{worst:.2%} of the most sensitive range"
                                        + ("" if worst < QUIET_FRACTION else ": enable line stuck on, or interference"))

    def signal():
        fe.start_excitation()
        fe.contact_current()
        wide = fe.step(pair, [channel], 0)
        best = fe.best_range(wide.volts)
        sample = fe.step(pair, [channel], best)
        state["on"], state["wide"] = sample, wide
        volts = float(sample.volts[0])
        floor = SIGNAL_OVER_ACCURACY * fe.profile.accuracy.absolute_v
        stuck = sample.codes[0] == state["off"].codes[channel]
        ok = abs(volts) > floor and sample.fraction[0] < OVER_RANGE and not stuck
        detail = f"source on reads {abs(volts) * 1e3:.3f} mV on electrodes 1-2 ({fe.ranges[best].label})"
        if stuck:
            detail += f"; the converter returned code {sample.codes[0]} with the source off and on: stuck"
        elif not ok:
            detail += ": no usable signal (sine source, current source or drive switches)"
        return ok, detail

    def ranges():
        on, wide = state["on"], state["wide"]
        if on.range_index == wide.range_index:
            return True, "the reading needs the wide range: the narrow one is not compared"
        ratio = float(on.volts[0] / wide.volts[0])
        ok = abs(ratio - 1) < GAIN_AGREEMENT
        wide_v, narrow_v = fe.ranges[wide.range_index].second_stage, fe.ranges[on.range_index].second_stage
        return ok, (f"+/-{wide_v:g} V and +/-{narrow_v:g} V agree to {abs(ratio - 1):.2%}"
                    + ("" if ok else ": RANGE pin or reference wrong"))

    try:
        check("converters with the source off", quiet)
        if results[-1].ok:
            check("sine, current source and drive switches", signal)
        if len(results) == 2 and results[-1].ok:
            check("AD7606 ranges", ranges)
    finally:
        fe.stop_excitation()
    return results
