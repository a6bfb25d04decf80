"""The scan engine: a protocol run on a front end, giving a frame of readings with quality flags.

Per reading it routes the multiplexers, picks the range (the most sensitive that
does not saturate: from the previous frame's plan, or by a probe at the least
sensitive range on the first frame), waits the settling the front end asks for,
converts, and checks what it got. Readings are taken drive pair by drive pair
(a drive switch is the slowest change) and, within a drive pair, in rising order
of the level the plan predicts, so the RMS converter only ever settles upwards,
which it does twice as fast.

A parallel front end (``front_end.parallel``) takes a drive's readings in one
step (:mod:`appliance.drivers.steps`): the engine routes each drive once, in
protocol order, with the next drive routed while the last is read out, and
ranges per drive. On a grid the engine also offers adaptive frames:
``scan(loaded=...)`` takes the coarse drives (along the rows) and only the fine
drives near the electrodes the caller marks as loaded
(:mod:`appliance.drivers.adaptive`); the readings of drives not taken keep the
last frame's values, flagged HELD (usable). An engine's first frame is always
a full pass, the reference the held values start from.

Faults: a transfer error is retried (``retries`` attempts in all) and then flags
that reading (on a parallel chain, that drive's readings) BUS_ERROR while the
scan goes on; electrodes that fail the contact check are not used
(OPEN_ELECTRODE); a reading over range at the least sensitive range is
SATURATED; a converter repeating one code across different readings is STUCK
(on a parallel chain, one AD7606 giving one code for every reading it converts);
reciprocal readings that disagree beyond the stated accuracy are flagged
RECIPROCITY. Contacts are checked every frame, or every ``[board.contact]
every_frames`` frames where the check is long (the parallel board's 256 steps).
Flagged-unusable readings are NaN in :attr:`AcquiredFrame.volts`, and
every fault is also a :class:`TechnicalCondition` naming the part.
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import cast

import numpy as np

from appliance.core.protocols import Protocol
from appliance.drivers.adaptive import AdaptivePlan
from appliance.drivers.bus import with_retries
from appliance.drivers.contact import ContactReport, check_contacts
from appliance.drivers.frontend import FrontEnd, Measured
from appliance.drivers.frontend_parallel import ParallelFrontEnd
from appliance.drivers.steps import stuck_converters, take_step
from appliance.errors import ApplianceError, ChipError, ConfigError, ScanError, TransferFailed

log = logging.getLogger(__name__)

LOW_SIGNAL = 0.02          # below this fraction at the most sensitive range the reading is mostly noise
STUCK_RUN = 4              # this many different readings giving one identical code means a stuck converter


class Flag(enum.IntFlag):
    """Quality of one reading; the first five make it unusable."""

    SATURATED = 1
    OPEN_ELECTRODE = 2
    BUS_ERROR = 4
    STUCK = 8
    RECIPROCITY = 16
    LOW_SIGNAL = 32
    SIGN_UNCERTAIN = 64
    HELD = 128              # not taken this frame (adaptive): the last frame's value, with its flags
    COMPLIANCE = 256        # the drive needed more than the source's compliance: scaled down (models only)


UNUSABLE = Flag.SATURATED | Flag.OPEN_ELECTRODE | Flag.BUS_ERROR | Flag.STUCK | Flag.RECIPROCITY


def flag_names(flags: int) -> str:
    """``"SATURATED|LOW_SIGNAL"`` for a flag word, ``""`` for a clean reading."""
    return "|".join(f.name for f in Flag if flags & f and f.name)


@dataclass(frozen=True)
class TechnicalCondition:
    """A fault of the equipment (not of the patient), naming the part: shown to the clinical engineer."""

    part: str
    message: str

    def __str__(self) -> str:
        return f"{self.part}: {self.message}"


@dataclass(frozen=True)
class AcquiredFrame:
    """One set of readings in protocol order.

    ``volts`` are V(meas+) - V(meas-) (volts rms at ``drive_current_a``), NaN where
    a flag makes the reading unusable; ``measured_volts`` keep what was measured
    anyway. ``time_s`` is when each reading was taken, from the frame's start.
    """

    protocol: Protocol
    volts: np.ndarray
    measured_volts: np.ndarray
    flags: np.ndarray
    range_index: np.ndarray
    fraction: np.ndarray
    time_s: np.ndarray
    duration_s: float
    drive_current_a: float
    contact: ContactReport | None
    conditions: tuple[TechnicalCondition, ...] = ()
    sets: int = 1
    temperature_c: float | None = None

    @property
    def usable(self) -> np.ndarray:
        return (self.flags & int(UNUSABLE)) == 0


SATURATION_PART = "measuring channel"


def saturation_condition(flags: np.ndarray, protocol: Protocol) -> TechnicalCondition | None:
    """The condition readings over range at the lowest gain raise, naming the measuring electrodes most
    involved (where to look for a bad contact or a short); None when no reading saturated."""
    saturated = (np.asarray(flags) & int(Flag.SATURATED)) != 0
    if not saturated.any():
        return None
    electrodes = protocol.readings[saturated][:, 2:].ravel()
    counts = np.bincount(electrodes, minlength=protocol.n_electrodes + 1)
    worst = [int(e) for e in np.flatnonzero(counts == counts.max())]
    return TechnicalCondition(
        SATURATION_PART, f"{int(saturated.sum())} readings over range even at the lowest gain; measuring "
        f"electrode(s) most involved: {', '.join(map(str, worst))}")


@dataclass
class _Tally:
    """What one scan gathers, in protocol order."""

    n: int
    volts: np.ndarray = field(init=False)
    flags: np.ndarray = field(init=False)
    ranges: np.ndarray = field(init=False)
    fraction: np.ndarray = field(init=False)
    times: np.ndarray = field(init=False)
    codes: np.ndarray = field(init=False)

    def __post_init__(self):
        self.volts = np.full(self.n, np.nan)
        self.flags = np.zeros(self.n, dtype=np.int64)
        self.ranges = np.full(self.n, -1, dtype=np.int64)
        self.fraction = np.full(self.n, np.nan)
        self.times = np.full(self.n, np.nan)
        self.codes = np.empty(self.n, dtype=object)


class ScanEngine:
    """Runs ``protocol`` on ``front_end``; keeps the range plan, the contact report and the last frame from one
    frame to the next. ``fine_radius`` (electrode spacings) is how near a loaded electrode an adaptive frame
    takes the fine drives."""

    def __init__(self, front_end: FrontEnd | ParallelFrontEnd, protocol: Protocol, *, order: str = "optimised",
                 retries: int = 3, conversions: int = 1, contact_check: bool = True,
                 progress: Callable[[int, int], None] | None = None, fine_radius: float = 2.0):
        if order not in ("optimised", "protocol"):
            raise ValueError(f"order must be 'optimised' or 'protocol', got {order!r}")
        if conversions < 1 or retries < 1:
            raise ValueError("conversions and retries must be at least 1")
        front_end.check_electrodes(protocol.n_electrodes)
        self.front_end, self.protocol, self.order = front_end, protocol, order
        self.retries, self.conversions, self.contact_check = retries, conversions, contact_check
        self.progress = progress
        self.plan_range: np.ndarray | None = None       # per reading, from the last frame
        self.plan_fraction: np.ndarray | None = None
        self.parallel = getattr(front_end, "parallel", False)
        if self.parallel:
            self.channels, self.signs = self._stepping.cmap.channels_of_protocol(protocol.readings)
            self.by_drive = [np.flatnonzero(protocol.drive_index == d) for d in range(len(protocol.drives))]
            self.plan_drive_range = np.full(len(protocol.drives), -1, dtype=np.int64)
        grid = front_end.profile.grid
        self.adaptive = AdaptivePlan(protocol, grid.rows, grid.cols, radius=fine_radius) if grid else None
        self.contact_every = front_end.profile.contact.every_frames or 1
        self.frames = 0
        self.contact: ContactReport | None = None       # the last contact check's report
        self.last: AcquiredFrame | None = None

    def drives_for(self, loaded) -> np.ndarray | None:
        """The drives a frame takes (indices into ``protocol.drives``), None for all: all until a first full frame
        has been taken, or when ``loaded`` is None; else the adaptive plan's for the ``loaded`` electrodes."""
        if loaded is None or self.last is None:
            return None
        if self.adaptive is None:
            raise ConfigError("adaptive frames need a front end built for a grid ([board.grid], the parallel "
                              "profile)")
        return self.adaptive.drives_for(loaded)

    # -- ordering ------------------------------------------------------------------------
    def reading_order(self) -> np.ndarray:
        """Indices of the protocol's readings in the order they will be taken."""
        n = len(self.protocol)
        if self.order == "protocol":
            return np.arange(n)
        level = np.zeros(n) if self.plan_fraction is None else self._planned_output()
        drive_rank = self.protocol.drive_index
        return np.lexsort((np.arange(n), level, drive_rank))

    @property
    def _stepping(self) -> ParallelFrontEnd:
        """The front end as a chain that reads every pair of a drive at once (``parallel``)."""
        return cast(ParallelFrontEnd, self.front_end)

    @property
    def _serial(self) -> FrontEnd:
        """The front end as a chain that takes one reading at a time (not ``parallel``)."""
        return cast(FrontEnd, self.front_end)

    def _planned_output(self) -> np.ndarray:
        """The RMS output level each reading is expected at (fraction x range full scale)."""
        fe = self._serial
        assert self.plan_range is not None and self.plan_fraction is not None     # called once planned
        scale = np.array([fe.output_scale(r) for r in range(len(fe.ranges))])
        return np.nan_to_num(self.plan_fraction) * scale[np.clip(self.plan_range, 0, None)]

    # -- one frame -------------------------------------------------------------------------
    def scan(self, loaded=None) -> AcquiredFrame:
        """Acquire one set: contact check, then the readings; the excitation is off afterwards.

        ``loaded`` (electrode numbers, any iterable) makes an adaptive frame; see the module docstring.
        """
        fe, clock = self.front_end, self.front_end.clock
        drives = self.drives_for(loaded)
        start = clock.monotonic()
        conditions: list[TechnicalCondition] = []
        tally = _Tally(len(self.protocol))
        try:
            temperature = self._temperature(conditions)
            contact = self._contact(conditions)
            if self.parallel:
                self._zero(conditions)
            self._start_excitation(conditions)
            blocked = contact.open_electrodes if contact else frozenset()
            if self.parallel:
                self._steps(drives, tally, conditions, start, blocked)
                self._find_stuck_converters(tally, conditions)
            else:
                order = self.reading_order()
                if drives is not None:
                    order = order[np.isin(self.protocol.drive_index[order], drives)]
                for done, i in enumerate(order, start=1):
                    row = self.protocol.readings[i]
                    if blocked & set(row.tolist()):
                        tally.flags[i] |= Flag.OPEN_ELECTRODE
                    else:
                        self._reading(i, row, tally, conditions, start)
                    if self.progress is not None:
                        self.progress(done, len(order))
                self._find_stuck(order, tally, conditions)
        finally:
            self._safe_state(conditions)
        self._check_drives(tally, conditions)
        self._check_reciprocity(tally, conditions)
        saturation = saturation_condition(tally.flags, self.protocol)
        if saturation is not None:
            conditions.append(saturation)
        self._update_plan(tally)
        self._hold(drives, tally)
        volts = np.where((tally.flags & int(UNUSABLE)) == 0, tally.volts, np.nan)
        if not np.isfinite(volts).any():
            conditions.append(TechnicalCondition("front end", "no usable reading in this frame"))
        frame = AcquiredFrame(self.protocol, volts, tally.volts, tally.flags, tally.ranges, tally.fraction,
                              tally.times, clock.monotonic() - start, fe.drive_current_a(), contact,
                              tuple(conditions), temperature_c=temperature)
        self.last = frame
        self.frames += 1
        return frame

    def _temperature(self, conditions) -> float | None:
        """The mat's temperature (its conductivity follows it, about 2 % per degree for saline)."""
        try:
            return with_retries(self.front_end.thermometer.temperature_c, attempts=self.retries,
                                what="MCP9808 thermometer")
        except TransferFailed as exc:
            conditions.append(TechnicalCondition("thermometer", str(exc)))
            return None

    def _contact(self, conditions) -> ContactReport | None:
        """A contact check when one is due (every frame, or every ``contact_every``); else the last report."""
        if not self.contact_check:
            return None
        if self.contact is None or self.frames % self.contact_every == 0:
            try:
                self.contact = check_contacts(self.front_end, self.protocol.n_electrodes, retries=self.retries)
            except TransferFailed as exc:
                conditions.append(TechnicalCondition("contact check", f"could not complete: {exc}"))
                self.contact = None
                return None
        report = self.contact
        for e in sorted(report.open_electrodes):
            conditions.append(TechnicalCondition(f"electrode {e}", "open or lost contact: its readings are "
                                                 "left out"))
        return report

    def _zero(self, conditions) -> None:
        """The parallel channels' offsets, with the source off; the last ones are kept if it fails."""
        fe = self._stepping
        try:
            with_retries(fe.measure_zero, attempts=self.retries, what="zero of the measuring channels",
                         on_retry=lambda *_: fe.forget_routing())
        except TransferFailed as exc:
            conditions.append(TechnicalCondition(fe.converter_name(), f"zero not measured ({exc}); the last "
                                                 "offsets are used"))
            fe.forget_routing()
        except ChipError as exc:
            raise ScanError(f"the converters do not respond: {exc}") from exc

    def _start_excitation(self, conditions) -> None:
        try:
            with_retries(self.front_end.start_excitation, attempts=self.retries, what="excitation start")
        except (TransferFailed, ApplianceError) as exc:
            raise ScanError(f"the excitation could not be started: {exc}") from exc

    def _safe_state(self, conditions) -> None:
        try:
            with_retries(self.front_end.stop_excitation, attempts=self.retries, what="excitation stop")
        except TransferFailed as exc:
            conditions.append(TechnicalCondition("current source", f"could not be switched off: {exc}"))

    def _reading(self, i: int, row, tally: _Tally, conditions, start: float) -> None:
        drive, measure = (int(row[0]), int(row[1])), (int(row[2]), int(row[3]))
        try:
            measured = with_retries(lambda: self._measure(i, drive, measure), attempts=self.retries,
                                    what=f"reading {i + 1} ({drive[0]},{drive[1]};{measure[0]},{measure[1]})",
                                    on_retry=lambda *_: self.front_end.forget_routing())
        except TransferFailed as exc:
            tally.flags[i] |= Flag.BUS_ERROR
            conditions.append(TechnicalCondition("bus", str(exc)))
            self.front_end.forget_routing()
            return
        sample, r = measured.sample, measured.range_index
        tally.volts[i], tally.ranges[i], tally.fraction[i] = sample.volts, r, sample.fraction
        tally.times[i], tally.codes[i] = self.front_end.clock.monotonic() - start, sample.raw
        if measured.saturated:
            tally.flags[i] |= Flag.SATURATED
        if r == len(self.front_end.ranges) - 1 and sample.fraction < LOW_SIGNAL:
            tally.flags[i] |= Flag.LOW_SIGNAL
        if not sample.sign_known:
            tally.flags[i] |= Flag.SIGN_UNCERTAIN

    def _measure(self, i: int, drive, measure) -> Measured:
        range_index: int | None = None
        expected_fraction: float | None = None
        if self.plan_range is not None and self.plan_fraction is not None and self.plan_range[i] >= 0:
            range_index, expected_fraction = int(self.plan_range[i]), float(self.plan_fraction[i])
        return self._serial.measure(drive, measure, range_index=range_index, expected_fraction=expected_fraction,
                                    conversions=self.conversions)

    def _steps(self, drives, tally: _Tally, conditions, start: float, blocked) -> None:
        """A parallel front end's readings: one step per drive, in protocol order."""
        fe, protocol = self._stepping, self.protocol
        blocked_electrodes = np.array(sorted(blocked), dtype=np.int64)
        runnable = []
        for d in (range(len(protocol.drives)) if drives is None else drives):
            idx = self.by_drive[d]
            if np.isin(protocol.drives[d], blocked_electrodes).any():
                tally.flags[idx] |= Flag.OPEN_ELECTRODE
                continue
            off = np.isin(protocol.readings[idx, 2:], blocked_electrodes).any(axis=1)
            tally.flags[idx[off]] |= Flag.OPEN_ELECTRODE
            if (~off).any():
                runnable.append((d, idx[~off]))
        floor = fe.profile.measurement.sign_floor_v
        done, total = 0, sum(len(idx) for _, idx in runnable)
        for n, (d, idx) in enumerate(runnable):
            source, sink = protocol.drives[d]
            drive = (int(source), int(sink))
            then: tuple[int, int] | None = None
            if n + 1 < len(runnable) and self.plan_drive_range[d] >= 0:
                source, sink = protocol.drives[runnable[n + 1][0]]
                then = (int(source), int(sink))
            try:
                # with_retries calls the action before the loop moves on, so it sees this drive's values.
                result = with_retries(
                    lambda: take_step(fe, drive, self.channels[idx], self.signs[idx],  # noqa: B023
                                      int(self.plan_drive_range[d]), then=then,  # noqa: B023
                                      conversions=self.conversions),
                    attempts=self.retries, what=f"drive {drive[0]}-{drive[1]}",
                    on_retry=lambda *_: fe.forget_routing())
            except TransferFailed as exc:
                tally.flags[idx] |= Flag.BUS_ERROR
                conditions.append(TechnicalCondition("bus", str(exc)))
                fe.forget_routing()
                continue
            self.plan_drive_range[d] = result.range_index
            tally.volts[idx], tally.fraction[idx] = result.volts, result.fraction
            tally.ranges[idx], tally.times[idx] = result.range_index, result.sampled_at_s - start
            for i, code in zip(idx, result.codes):
                tally.codes[i] = code
            tally.flags[idx[result.saturated]] |= Flag.SATURATED
            quiet = idx[(np.abs(result.volts) < floor) & ~result.saturated]
            tally.flags[quiet] |= Flag.LOW_SIGNAL | Flag.SIGN_UNCERTAIN
            done += len(idx)
            if self.progress is not None:
                self.progress(done, total)

    def _find_stuck_converters(self, tally: _Tally, conditions) -> None:
        quiet = int(Flag.LOW_SIGNAL | Flag.SATURATED)
        stuck = stuck_converters(tally.codes, (tally.flags & quiet) == 0, tally.times, run=STUCK_RUN)
        for adc, code in sorted(stuck.items()):
            mine = np.array([c is not None and c[0] == adc for c in tally.codes])
            tally.flags[mine] |= Flag.STUCK
            conditions.append(TechnicalCondition(self._stepping.converter_name(adc),
                                                 f"returned code {code} for every reading it converted: stuck"))

    def _hold(self, drives, tally: _Tally) -> None:
        """Readings of drives not taken this frame keep the last frame's values and flags, flagged HELD."""
        if drives is None:
            return
        held = ~np.isin(self.protocol.drive_index, drives)
        last = self.last
        assert last is not None                 # drives are chosen only once a full frame was taken
        tally.volts[held], tally.fraction[held] = last.measured_volts[held], last.fraction[held]
        tally.ranges[held], tally.flags[held] = last.range_index[held], last.flags[held] | Flag.HELD

    # -- checks over the frame -------------------------------------------------------------
    def _find_stuck(self, order, tally: _Tally, conditions) -> None:
        run: list[int] = []
        stuck_code = None
        for i in order:
            code = tally.codes[i]
            if code is None or tally.flags[i] & Flag.LOW_SIGNAL:
                continue          # a repeated near-zero code is no signal, which _check_drives reports
            if run and code == tally.codes[run[-1]]:
                run.append(i)
            else:
                run = [i]
            if len(run) >= STUCK_RUN:
                tally.flags[run] |= Flag.STUCK
                stuck_code = code
        if stuck_code is not None:
            conditions.append(TechnicalCondition(self.front_end.converter_name(),
                                                 f"returned code {stuck_code} for {STUCK_RUN} or more different "
                                                 "readings in a row: stuck"))

    def _check_drives(self, tally: _Tally, conditions) -> None:
        """A drive pair whose every reading is noise carries no current: an open drive electrode."""
        measured = tally.ranges >= 0
        quiet = (tally.flags & int(Flag.LOW_SIGNAL)) != 0
        for d, (a, b) in enumerate(self.protocol.drives.tolist()):
            mine = (self.protocol.drive_index == d) & measured & ((tally.flags & int(Flag.SATURATED)) == 0)
            if mine.any() and quiet[mine].all():
                tally.flags[self.protocol.drive_index == d] |= Flag.OPEN_ELECTRODE
                conditions.append(TechnicalCondition(f"drive pair {a}-{b}", "no signal on any reading: the "
                                                     "current does not flow (open drive electrode or source)"))

    def _check_reciprocity(self, tally: _Tally, conditions) -> None:
        accuracy = self.front_end.profile.accuracy
        pairs = self.protocol.reciprocal_pairs()
        bad = 0
        for i, j in pairs:
            vi, vj = tally.volts[i], tally.volts[j]
            if not (np.isfinite(vi) and np.isfinite(vj)) or (tally.flags[[i, j]] & int(UNUSABLE)).any():
                continue
            allowed = 3 * (accuracy.relative * max(abs(vi), abs(vj)) + accuracy.absolute_v)
            if abs(vi - vj) > allowed:
                tally.flags[[i, j]] |= Flag.RECIPROCITY
                bad += 1
        if bad:
            conditions.append(TechnicalCondition("measurement", f"{bad} of {len(pairs)} reciprocal pairs disagree "
                                                 "beyond the stated accuracy"))

    def _update_plan(self, tally: _Tally) -> None:
        fresh = tally.ranges >= 0
        if self.plan_range is None:
            self.plan_range = np.full(len(self.protocol), -1, dtype=np.int64)
            self.plan_fraction = np.full(len(self.protocol), np.nan)
        assert self.plan_fraction is not None
        self.plan_range[fresh] = tally.ranges[fresh]
        self.plan_fraction[fresh] = tally.fraction[fresh]


def average_frames(frames: list[AcquiredFrame]) -> AcquiredFrame:
    """The thesis's "average of N sets": per reading, the mean over the sets where it was usable.

    A reading usable in no set keeps every flag it got and stays NaN; one usable
    in some sets keeps only the warning flags. Conditions of all sets are kept.
    """
    if not frames:
        raise ValueError("no frames to average")
    volts, count = _mean_finite([f.volts for f in frames])
    measured, _ = _mean_finite([f.measured_volts for f in frames])
    flags = np.bitwise_or.reduce(np.array([f.flags for f in frames]), axis=0)
    flags = np.where(count > 0, flags & ~int(UNUSABLE), flags)
    last = frames[-1]
    conditions = tuple(dict.fromkeys(c for f in frames for c in f.conditions))
    return AcquiredFrame(last.protocol, volts, measured, flags, last.range_index, last.fraction, last.time_s,
                         sum(f.duration_s for f in frames), last.drive_current_a, last.contact, conditions,
                         sets=len(frames), temperature_c=last.temperature_c)


def _mean_finite(rows) -> tuple[np.ndarray, np.ndarray]:
    """Column means over the finite entries (NaN where none) and how many there were."""
    stack = np.array(rows, dtype=float)
    finite = np.isfinite(stack)
    count = finite.sum(axis=0)
    total = np.where(finite, stack, 0.0).sum(axis=0)
    return np.where(count > 0, total / np.maximum(count, 1), np.nan), count
