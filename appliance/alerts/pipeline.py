"""From pressure maps to alarms: regions, dose, turn clock and the alarm engine, frame by frame.

Each frame: the regions at or above the threshold are tracked; every pixel's
pressure-time dose is accumulated against the tolerance curve; the turn clock
looks for repositioning. A region whose tissue has used its tolerance
(dose >= 1 on any of its pixels) is a clinical alarm condition, keyed by its zone
and identity, so the nurse is told which site; an overdue turn is a reminder.
Technical conditions (no data, electrode fault, saturation, bus error) come
from the caller and stay apart. The engine turns conditions into alarm events.

Priorities follow the appliance's IEC 60601-1-8 mapping (clinical-anchors.md,
section 3.1): tissue damage from sustained pressure is delayed-onset and may be
irreversible, so MEDIUM, escalated to the ward station when unacknowledged; the
turn reminder is LOW; equipment faults that stop monitoring are MEDIUM.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from appliance.alerts.alarms import AlarmCondition, AlarmEngine, AlarmEvent, Escalation
from appliance.alerts.dose import MAX_DT_S, DoseMap, custom_curve, tolerance_curve
from appliance.alerts.regions import RegionTracker
from appliance.alerts.turns import DEFAULT_INTERVAL_S, TurnEvent, turn_clock_for
from appliance.core.pixels import PixelGrid
from appliance.core.pressure_map import HIGH_PRESSURE_KPA, PressureMap

ESCALATE_AFTER_S = 15 * 60.0
MAX_COUNTED_GAP_S = 12 * 3600.0
"""A gap between maps (the monitor off, or paused for maintenance) counts as the new map's pressure held since
the last one, as every frame does, up to this long: by then any loaded tissue is long past its tolerance, and a
clock that jumped by years must not stall the loop."""


@dataclass(frozen=True)
class AlertSettings:
    """What a ward configures: threshold, tolerance curve (a built-in's name, or ``curve_points`` of
    (minutes, mmHg) with ``curve`` naming them), dose at which to alarm, recovery, turn interval."""

    threshold_kpa: float = HIGH_PRESSURE_KPA
    curve: str = "reswick-rogers"
    curve_points: tuple[tuple[float, float], ...] | None = None
    recovery: str = "reset"
    alarm_dose: float = 1.0
    turn_interval_s: float = DEFAULT_INTERVAL_S
    escalate_after_s: float = ESCALATE_AFTER_S
    escalation_channel: str = "ward-station"


@dataclass(frozen=True)
class FrameAlerts:
    """What one frame brought: alarm and turn events, and each tracked region's dose."""

    alarm_events: list[AlarmEvent]
    turn_events: list[TurnEvent]
    region_doses: dict[int, float] = field(default_factory=dict)


def technical_alarms(conditions) -> dict[str, str]:
    """A frame's technical conditions (``part``, ``message``) as the pipeline's technical alarm keys."""
    return {f"technical:{c.part.replace(' ', ':')}": f"{c.part}: {c.message}" for c in conditions}


def _technical(technical: dict[str, str] | None) -> dict:
    return {key: (AlarmCondition(key, "technical", "medium", False, message), None)
            for key, message in (technical or {}).items()}


class AlertPipeline:
    """Regions, dose, turns and alarms for one mat's pixel grid."""

    def __init__(self, grid: PixelGrid, settings: AlertSettings = AlertSettings()):
        self.grid, self.settings = grid, settings
        if settings.curve_points:
            self.curve = custom_curve(settings.curve_points, name=settings.curve, floor_kpa=settings.threshold_kpa)
        else:
            self.curve = tolerance_curve(settings.curve, floor_kpa=settings.threshold_kpa)
        self.regions = RegionTracker(grid, threshold_kpa=settings.threshold_kpa)
        self.dose = DoseMap(grid.shape, self.curve, recovery=settings.recovery)
        self.turns = turn_clock_for(grid, interval_s=settings.turn_interval_s, at_risk_kpa=settings.threshold_kpa)
        self.engine = AlarmEngine()
        self.last_time_s: float | None = None
        self.clinical: dict[str, tuple[AlarmCondition, str | None]] = {}   # the last map's clinical conditions
        self.tracked: list = []                                              # the last map's regions

    def update(self, pressure_map: PressureMap, technical: dict[str, str] | None = None) -> FrameAlerts:
        """One frame; ``technical`` maps a technical condition's key (``"technical:electrode:5"``) to its
        message while it holds."""
        now = pressure_map.time_s
        if self.last_time_s is not None and now > self.last_time_s:
            gap = min(now - self.last_time_s, MAX_COUNTED_GAP_S)
            while gap > 0:                          # a gap (a restart, a pause for maintenance) in steps
                step = min(gap, MAX_DT_S)
                self.dose.update(pressure_map.pressure_kpa, step)
                gap -= step
        self.last_time_s = now
        tracked = self.tracked = self.regions.update(pressure_map)
        doses = {r.id: self.dose.fraction(r.mask) for r in tracked}
        turn_events = self.turns.update(pressure_map)
        active = {}
        for region in tracked:
            if doses[region.id] >= self.settings.alarm_dose:
                condition = self._pressure_condition(region)
                active[condition.key] = (condition, f"{doses[region.id]:.2f} of the tolerance used")
        due = self.turns.due_in_s(now)
        if due is not None and due <= 0 and self.turns.candidate_since is None:    # not while a turn settles
            condition = AlarmCondition("turn:due", "clinical", "low", False, "repositioning is due")
            active[condition.key] = (condition, f"{max(0.0, -due) / 60:.0f} min overdue")
        self.clinical = dict(active)
        return FrameAlerts(self.engine.assess(now, {**active, **_technical(technical)}), turn_events, doses)

    def hold(self, now_s: float, technical: dict[str, str]) -> FrameAlerts:
        """A frame time with no map: technical alarms move on, clinical ones stay as the last map left them.

        Without a map nothing is known of the skin, so no clinical alarm may end
        for want of data; the dose of the gap is added with the next map.
        """
        return FrameAlerts(self.engine.assess(now_s, {**self.clinical, **_technical(technical)}), [])

    def _pressure_condition(self, region) -> AlarmCondition:
        site = region.zone or "region"
        s = self.settings
        return AlarmCondition(f"pressure:{site}:{region.id}", "clinical", "medium", False,
                              f"sustained pressure at the {site}: reposition the patient",
                              (Escalation(s.escalate_after_s, s.escalation_channel),))

    def state(self) -> dict:
        """Everything needed to carry on after a restart, as plain JSON types."""
        return {"regions": self.regions.state(), "dose": self.dose.state(), "turns": self.turns.state(),
                "alarms": self.engine.state(), "last_time_s": self.last_time_s,
                "clinical": [[c.to_dict(), detail] for c, detail in self.clinical.values()]}

    @classmethod
    def from_state(cls, grid: PixelGrid, state: dict, settings: AlertSettings = AlertSettings()) -> "AlertPipeline":
        """The pipeline :meth:`state` saved, continued under ``settings``.

        Patient settings changed since (by a nurse, or in the configuration while
        the monitor was down) apply from now on: the dose map takes the new
        curve, recovery and relief level (the threshold), and each pixel's dose,
        the share of its tolerance already used, carries over unchanged.
        """
        pipeline = cls(grid, settings)
        pipeline.regions = RegionTracker.from_state(grid, state["regions"], threshold_kpa=settings.threshold_kpa)
        dose = {**state["dose"], "curve": pipeline.curve.name, "recovery": settings.recovery,
                "relief_kpa": pipeline.dose.relief_kpa}
        pipeline.dose = DoseMap.from_state(dose, pipeline.curve)
        pipeline.turns.restore(state["turns"])
        pipeline.engine = AlarmEngine.from_state(state["alarms"])
        pipeline.last_time_s = state["last_time_s"]
        pipeline.clinical = {c["key"]: (AlarmCondition.from_dict(c), detail) for c, detail in state.get("clinical", [])}
        return pipeline
