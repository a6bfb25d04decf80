"""History: each loaded region's pressure and dose over the last hours, the turns and alarms, and a shift summary.

A nurse taking over a bed needs to know what happened since the last handover:
which sites bore pressure and for how long, how much of their tolerance they
used, when the patient was turned and which alarms were raised and how fast
someone answered them. Everything comes from the monitor's store (the maps and
regions it keeps every ``history_interval_s``, and its event log); nothing is
written. The charts are inline SVG drawn here, so the page needs no script,
prints as it looks and can be checked by a test.

The window is the last ``hours`` (1 to 168, 12 by default: a shift) up to the
store's newest record, on the monitor's own clock. A region counts as above the
threshold from each kept map where its peak is at or above it until the next
kept map (or the end of the window): the history's resolution, not the frame's.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

from flask import Blueprint, abort, jsonify, render_template, request

from appliance.alerts.alarms import PRIORITIES
from appliance.alerts.pipeline import AlertSettings
from appliance.alerts.anatomy import SITES, SMALL_MAT_SITE, UNIDENTIFIED_SITE, site_words
from appliance.alerts.turns import TURN_KINDS as TURN_EVENT_KINDS
from appliance.alerts.wording import alarm_words
from appliance.core.pressure import KPA_PER_MMHG
from appliance.store import Store
from appliance.time_zones import WALL_CLOCK_AFTER_S, local_time
from webui.alarms import reader
from webui.clocks import clock, zone
from webui.live import snapshot

bp = Blueprint("history", __name__)

DEFAULT_HOURS, MIN_HOURS, MAX_HOURS = 12.0, 1.0, 168.0
TURN_KINDS = TURN_EVENT_KINDS
"""The turn clock's event kinds (``appliance.alerts.turns.TurnEvent``); a turn is ``repositioned`` (seen) or
``recorded`` (by hand)."""
TURNED = ("repositioned", "recorded")
NO_HISTORY = "no history recorded yet"

CHART_W, CHART_H = 760, 200
LEFT, RIGHT, TOP, BOTTOM = 46, 42, 10, 22
TICK_STEPS_S = (600, 900, 1800, 3600, 2 * 3600, 3 * 3600, 6 * 3600, 12 * 3600, 24 * 3600)
MAX_TIME_TICKS = 8


# Reading the request and the store.

def requested_hours() -> float:
    """The ``hours`` query parameter (default 12); a 400 naming it and its range if it is not one."""
    raw = request.args.get("hours")
    if raw is None:
        return DEFAULT_HOURS
    try:
        hours = float(raw)
    except ValueError:
        hours = math.nan
    if not (math.isfinite(hours) and MIN_HOURS <= hours <= MAX_HOURS):
        abort(400, description=f"hours must be a number from {MIN_HOURS:g} to {MAX_HOURS:g}, got {raw!r}")
    return hours


def threshold_mmhg(live: dict) -> float:
    """The pressure threshold: the live snapshot's ``settings.threshold_kpa`` if it has one, else the default."""
    kpa = (live.get("settings") or {}).get("threshold_kpa", AlertSettings().threshold_kpa)
    return float(kpa) / KPA_PER_MMHG


@dataclass(frozen=True)
class History:
    """What the store holds for one window: kept map times, their regions, and the turn and alarm events."""

    start_s: float
    end_s: float
    map_times: list[float]
    regions: list[dict]
    turns: list[dict]
    alarms: list[dict]


def load_history(hours: float) -> History | None:
    """The last ``hours`` up to the store's newest record; None when it has recorded nothing."""
    with reader() as s:
        return read_history(s, hours)


def read_history(s: Store, hours: float) -> History | None:
    """:func:`load_history` from an open store (the command line's shift report has no app)."""
    end = s.last_time()
    if end is None:
        return None
    start = end - hours * 3600.0
    map_times = [t for t, _ in s.history_between(start, end)]
    regions = s.regions_between(start, end)
    events = [e for e in s.events_since(start) if e["time_s"] <= end]
    turns = [e for e in events if is_turn(e)]
    alarms = [e for e in events if not is_turn(e)]
    first = min(map_times[:1] + [e["time_s"] for e in events[:1]], default=start)
    return History(max(start, first), end, map_times, regions, turns, alarms)


def is_turn(event: dict) -> bool:
    """A turn clock event (an ``Event`` of type turn, or a bare ``TurnEvent``); the rest are alarm events."""
    return event.get("type") == "turn" or (event.get("type") is None and event["kind"] in TURN_KINDS)


# Series and summary: pure functions of the history.

@dataclass(frozen=True)
class RegionSeries:
    """One tracked region over the window: its samples at the kept maps, oldest first."""

    region_id: int
    zone: str | None
    times: list[float]
    peak_mmhg: list[float]
    dose: list[float | None]
    sites: tuple[str, ...] = ()

    @property
    def label(self) -> str:
        words = site_words(self.zone) if self.zone in (*SITES, SMALL_MAT_SITE, UNIDENTIFIED_SITE) else self.zone
        return f"{words} (region {self.region_id})" if self.zone else f"region {self.region_id}"


def region_series(rows: list[dict]) -> list[RegionSeries]:
    """The store's region rows grouped by region id, in id order; the zone is the latest site recorded in it,
    ``sites`` every one (a region's alarms are its sites')."""
    grouped: dict[int, list[dict]] = {}
    for row in rows:
        grouped.setdefault(row["region_id"], []).append(row)
    return [RegionSeries(region_id, next((r["zone"] for r in reversed(samples) if r["zone"]), None),
                         [r["time_s"] for r in samples], [r["peak_mmhg"] for r in samples],
                         [r["dose"] for r in samples], tuple(sorted({r["zone"] for r in samples if r["zone"]})))
            for region_id, samples in sorted(grouped.items())]


def minutes_above(series: RegionSeries, map_times: list[float], end_s: float, threshold: float) -> float:
    """Minutes the region's peak was at or above ``threshold``: each such sample holds until the next kept map."""
    following = dict(zip(map_times, map_times[1:] + [end_s]))
    held = sum(following.get(t, t) - t for t, peak in zip(series.times, series.peak_mmhg) if peak >= threshold)
    return held / 60.0


def longest_without_turn_s(turn_times: list[float], start_s: float, end_s: float) -> float:
    """The longest stretch of ``start_s``..``end_s`` with no turn in it."""
    edges = [start_s] + sorted(t for t in turn_times if start_s <= t <= end_s) + [end_s]
    return max(b - a for a, b in itertools.pairwise(edges))


@dataclass(frozen=True)
class AlarmRecord:
    """One alarm raised in the window: who acknowledged it and how long that took."""

    alarm_id: int
    key: str
    category: str
    priority: str
    highest_priority: str
    message: str
    raised_s: float
    acknowledged_by: str | None = None
    acknowledged_s: float | None = None
    ended_s: float | None = None

    @property
    def acknowledge_delay_s(self) -> float | None:
        return None if self.acknowledged_s is None else self.acknowledged_s - self.raised_s


def alarm_records(events: list[dict]) -> list[AlarmRecord]:
    """The alarms raised among ``events``, in order raised, with their acknowledgement, escalation and end."""
    records: dict[int, dict] = {}
    for e in events:
        alarm_id = e.get("alarm_id")
        if e["kind"] == "raised" and alarm_id is not None:
            records[alarm_id] = {"alarm_id": alarm_id, "key": e["key"], "category": e["category"],
                                 "priority": e["priority"], "highest_priority": e["priority"],
                                 "message": e.get("message") or "", "raised_s": e["time_s"]}
            continue
        record = records.get(alarm_id) if alarm_id is not None else None
        if record is None:
            continue
        if e["kind"] == "acknowledged" and record.get("acknowledged_s") is None:
            record.update(acknowledged_by=e.get("user"), acknowledged_s=e["time_s"])
        elif e["kind"] == "escalated" and e.get("priority") in PRIORITIES:
            record["highest_priority"] = max(record["highest_priority"], e["priority"], key=PRIORITIES.index)
        elif e["kind"] == "ended":
            record["ended_s"] = e["time_s"]
    return [AlarmRecord(**r) for r in records.values()]


@dataclass(frozen=True)
class RegionSummary:
    """One region over the shift: its highest peak and dose, and how long it was at or above the threshold."""

    label: str
    peak_mmhg: float
    max_dose: float | None
    minutes_above: float


@dataclass(frozen=True)
class ShiftSummary:
    """What a handover needs: turns, each region's worst, and the alarms (clinical and technical apart)."""

    start_s: float
    end_s: float
    threshold_mmhg: float
    turns: int
    turn_reminders: int
    longest_without_turn_s: float
    regions: list[RegionSummary]
    clinical: list[AlarmRecord]
    technical: list[AlarmRecord]


def summarise(history: History, threshold: float) -> ShiftSummary:
    """The shift summary of ``history`` against a pressure ``threshold`` in mmHg."""
    turn_times = [e["time_s"] for e in history.turns if e["kind"] in TURNED]
    regions = [RegionSummary(s.label, max(s.peak_mmhg), max((d for d in s.dose if d is not None), default=None),
                             minutes_above(s, history.map_times, history.end_s, threshold))
               for s in region_series(history.regions)]
    alarms = alarm_records(history.alarms)
    return ShiftSummary(history.start_s, history.end_s, threshold, len(turn_times),
                        sum(e["kind"] == "raised" and (e.get("key") or "").startswith("turn:")
                            for e in history.alarms),
                        longest_without_turn_s(turn_times, history.start_s, history.end_s), regions,
                        [a for a in alarms if a.category != "technical"],
                        [a for a in alarms if a.category == "technical"])


# Charts: geometry here, markup in the template.

@dataclass(frozen=True)
class Marker:
    """A vertical line on a chart at ``x``, with the event it stands for as its tooltip."""

    x: float
    kind: str           # turn, raised or acknowledged: the CSS class
    title: str


@dataclass(frozen=True)
class Chart:
    """One region's chart in SVG user units: polylines (one per unbroken run), guide lines, ticks and markers."""

    label: str
    pressure: list[str]
    dose: list[str]
    threshold_y: float
    dose_one_y: float
    pressure_ticks: list[tuple[float, str]]
    dose_ticks: list[tuple[float, str]]
    time_ticks: list[tuple[float, str]]
    markers: list[Marker]
    width: int = CHART_W
    height: int = CHART_H
    left: int = LEFT
    right: int = CHART_W - RIGHT
    top: int = TOP
    bottom: int = CHART_H - BOTTOM


def chart(series: RegionSeries, history: History, threshold: float) -> Chart:
    """The chart of one region: peak pressure (left axis, mmHg) and dose (right axis), turns and its alarms."""
    span = max(history.end_s - history.start_s, 1.0)

    def x(t: float) -> float:
        return round(LEFT + (t - history.start_s) / span * (CHART_W - LEFT - RIGHT), 1)

    pressure_top = 20.0 * math.ceil(max(max(series.peak_mmhg), threshold * 1.25) / 20.0)
    doses = [d for d in series.dose if d is not None]
    dose_top = max(1.25, math.ceil(max(doses, default=0.0) * 1.05 * 4) / 4)

    def y(value: float, top: float) -> float:
        return round(CHART_H - BOTTOM - value / top * (CHART_H - BOTTOM - TOP), 1)

    runs = unbroken_runs(series, history.map_times)
    markers = [Marker(x(e["time_s"]), "turn", f"{e['kind']} {clock(e['time_s'])}") for e in history.turns]
    markers += [Marker(x(e["time_s"]), e["kind"], f"alarm {e['kind']}: {alarm_words(e.get('key'))} {clock(e['time_s'])}"
                       + (f" by {e['user']}" if e.get("user") else ""))
                for e in history.alarms
                if e["kind"] in ("raised", "acknowledged") and e.get("site") in (None, *series.sites)]
    dose_step = 0.25 if dose_top <= 1.5 else 0.5
    return Chart(
        series.label,
        [" ".join(f"{x(t)},{y(p, pressure_top)}" for t, p, _ in run) for run in runs],
        [" ".join(f"{x(t)},{y(d, dose_top)}" for t, _, d in part)
         for run in runs for part in split_at_none(run)],
        y(threshold, pressure_top), y(1.0, dose_top),
        [(y(v, pressure_top), f"{v:g}") for v in frange(0.0, pressure_top, pressure_top / 4)],
        [(y(v, dose_top), f"{v:g}") for v in frange(0.0, dose_top, dose_step)],
        [(x(t), tick_label(t, span)) for t in time_ticks(history.start_s, history.end_s, utc_offset(history.start_s))],
        markers)


def unbroken_runs(series: RegionSeries, map_times: list[float]) -> list[list[tuple[float, float, float | None]]]:
    """The samples split where a kept map did not have the region (it was not loaded then), so no line bridges it."""
    index = {t: i for i, t in enumerate(map_times)}
    runs: list[list] = []
    previous = None
    for sample in zip(series.times, series.peak_mmhg, series.dose):
        position = index.get(sample[0])
        if not runs or position is None or previous is None or position != previous + 1:
            runs.append([])
        runs[-1].append(sample)
        previous = position
    return runs


def split_at_none(run: list[tuple]) -> list[list[tuple]]:
    """A run's stretches where the dose is known."""
    parts: list[list] = [[]]
    for sample in run:
        if sample[2] is None:
            parts.append([])
        else:
            parts[-1].append(sample)
    return [p for p in parts if p]


def frange(start: float, stop: float, step: float) -> list[float]:
    """``start``, ``start + step``, ... up to and including ``stop``."""
    return [start + i * step for i in range(round((stop - start) / step) + 1)]


def time_ticks(start_s: float, end_s: float, offset_s: float = 0.0) -> list[float]:
    """Times across the window round on a clock ``offset_s`` ahead of UTC (hours at :00 in India too, days at
    local midnight), at most ``MAX_TIME_TICKS`` of them."""
    span = end_s - start_s
    step = next((s for s in TICK_STEPS_S if span / s <= MAX_TIME_TICKS), TICK_STEPS_S[-1])
    first = math.ceil((start_s + offset_s) / step) * step - offset_s
    return [t for t in frange(first, end_s, step) if t <= end_s] if first <= end_s else []


def utc_offset(time_s: float) -> float:
    """How far the site's clock is ahead of UTC at ``time_s`` (none for a simulated bed's seconds)."""
    if time_s <= WALL_CLOCK_AFTER_S:
        return 0.0
    offset = local_time(time_s, zone()).utcoffset()
    return 0.0 if offset is None else offset.total_seconds()


def tick_label(time_s: float, span_s: float) -> str:
    """A tick's time, short: HH:MM in the site's zone (with the weekday over a day) for wall-clock times, h:mm for
    simulated ones."""
    if time_s > WALL_CLOCK_AFTER_S:
        return local_time(time_s, zone()).strftime("%a %H:%M" if span_s > 24 * 3600 else "%H:%M")
    minutes = round(time_s / 60)
    return f"{minutes // 60}:{minutes % 60:02d}"


def duration(seconds: float | None) -> str:
    """A duration as a nurse says it: 45 s, 5 min, 3 h 19 min; a dash when there is none."""
    if seconds is None:
        return "-"
    if seconds < 60:
        return f"{seconds:.0f} s"
    minutes = round(seconds / 60)
    return f"{minutes} min" if minutes < 60 else f"{minutes // 60} h {minutes % 60} min"


# Routes.

@bp.route("/history")
def page():
    hours = requested_hours()
    history = load_history(hours)
    threshold = threshold_mmhg(snapshot())
    charts = [] if history is None else [chart(s, history, threshold) for s in region_series(history.regions)]
    return render_template("history.html", hours=hours, history=history, charts=charts, threshold=threshold,
                           clock=clock, no_history=NO_HISTORY)


@bp.route("/api/history")
def data():
    hours = requested_hours()
    history = load_history(hours)
    threshold = threshold_mmhg(snapshot())
    if history is None:
        return jsonify({"hours": hours, "threshold_mmhg": threshold, "regions": [], "turns": [], "alarms": [],
                        "message": NO_HISTORY})
    return jsonify({"hours": hours, "from_s": history.start_s, "to_s": history.end_s, "threshold_mmhg": threshold,
                    "regions": [{"region_id": s.region_id, "zone": s.zone, "label": s.label, "times": s.times,
                                 "peak_mmhg": s.peak_mmhg, "dose": s.dose} for s in region_series(history.regions)],
                    "turns": history.turns, "alarms": history.alarms})


@bp.route("/history/summary")
def summary():
    hours = requested_hours()
    history = load_history(hours)
    live = snapshot()
    result = None if history is None else summarise(history, threshold_mmhg(live))
    return render_template("shift_summary.html", hours=hours, summary=result, bed_id=live.get("bed_id"),
                           clock=clock, duration=duration, no_history=NO_HISTORY)
