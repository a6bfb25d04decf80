"""From pressure maps to alarms about a body: posture, tissue sites, dose per site, turns, reminders, episodes.

Each frame on a bed: the map is seen as the body (:mod:`appliance.alerts.anatomy`);
its posture is estimated (:mod:`appliance.alerts.posture`) and its loaded spots are
named as tissue sites from that posture and the body's outline
(:mod:`appliance.alerts.sites`); each site's pressure-time dose grows by its peak
against the tolerance curve (:class:`~appliance.alerts.dose.SiteDose`), keyed by
the site, so it follows the body wherever it lies and whatever the map's
segmentation does; the turn clock watches posture and sites for repositionings
(:mod:`appliance.alerts.turns`). A site whose dose reaches the alarm dose is a
clinical alarm condition keyed by the site (``pressure:heel-left``); an owed turn
is a graded reminder; leaving the bed alerts when the patient's episode asks for
it. Loaded regions are still tracked for the screen and the history, each named
by the site it holds.

On a small mat (a test sensor, no body on it) the whole mat is one site,
``mat``, and no turn is watched. Load on a bed too light to be a body (heels
alone on the mat) is one site too, ``unidentified``, placed at its peak: no
site can be named without a body, but no loaded tissue goes unwatched.

Technical conditions (no data, electrode fault, saturation, bus error) come from
the caller and stay apart. The engine turns conditions into alarm events; every
event leaves here as a record (:mod:`appliance.alerts.events`) that names the
site, its place on the mat (mm), the posture and the patient.

Priorities follow the appliance's IEC 60601-1-8 mapping (clinical-anchors.md,
section 3.1): tissue damage from sustained pressure is delayed-onset and may be
irreversible, so MEDIUM, escalated to the ward station when unacknowledged; a
turn falling due is MEDIUM and an overdue one HIGH; equipment faults that stop
monitoring are MEDIUM.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from appliance.alerts.alarms import AlarmCondition, AlarmEngine, AlarmEvent, Escalation
from appliance.alerts.anatomy import (SITES, SMALL_MAT_SITE, UNIDENTIFIED_SITE, BodyView, body_view, in_bed,
                                     is_bed, posture_group, site_words)
from appliance.alerts.dose import MAX_DT_S, RELIEF_S, SiteDose, ToleranceCurve, custom_curve, tolerance_curve
from appliance.alerts.episodes import Episode
from appliance.alerts.events import Event, as_event
from appliance.alerts.posture import PostureEstimate
from appliance.alerts.regions import RegionTracker
from appliance.alerts.turns import DEFAULT_GRACE_S, DEFAULT_INTERVAL_S, DEFAULT_REPEAT_S, TurnClock, TurnEvent
from appliance.core.pixels import PixelGrid
from appliance.core.pressure_map import HIGH_PRESSURE_KPA, PressureMap
from appliance.errors import ConfigError

ESCALATE_AFTER_S = 15 * 60.0
OVERDUE_ESCALATE_S = 60.0             # an overdue reminder reaches the ward station after a minute unanswered
FOLLOW_MM = 45.0
"""A loaded site the locator does not name on a map keeps being dosed with the load where it last lay, within this
distance (one and a half 30 mm pixels: a restless patient's shift between two namings), as long as the patient
lies in the posture group it was named in: the tissue is still loaded whatever the names do. A turn to another
group ends it. A site last named below the threshold keeps the peak it was named with instead: the load within
reach of it is a neighbour's (a spine or a blade beside it), not its own, and a site named at 25 mmHg a minute ago
is not offloaded now either (the turn clock would count it so). Following such a site, a held-out subject's
shoulder blade flickering in and out of the locator's names at 22 mmHg took a neighbour's 35 mmHg in turn, never
relieved over a 2-hour tilt and raised a false alarm through the chain; over the training subjects' nights the rule
changes no alarm (benchmarks/training_nights.md)."""
MAX_COUNTED_GAP_S = 12 * 3600.0
"""A gap between maps (the monitor off, or paused for maintenance) counts as the new map's pressure held since
the last one, as every frame does, up to this long: by then any loaded tissue is long past its tolerance, and a
clock that jumped by years must not stall the loop."""


@dataclass(frozen=True)
class AlertSettings:
    """What a ward configures: threshold, tolerance curve (a built-in's name, or ``curve_points`` of
    (minutes, mmHg) with ``curve`` naming them), dose at which to alarm, recovery and its time, turn interval,
    the grace before a due turn is overdue and how often an overdue reminder repeats, escalation."""

    threshold_kpa: float = HIGH_PRESSURE_KPA
    curve: str = "reswick-rogers"
    curve_points: tuple[tuple[float, float], ...] | None = None
    recovery: str = "reset"
    relief_s: float = RELIEF_S
    alarm_dose: float = 1.0
    turn_interval_s: float = DEFAULT_INTERVAL_S
    turn_grace_s: float = DEFAULT_GRACE_S
    reminder_repeat_s: float = DEFAULT_REPEAT_S
    escalate_after_s: float = ESCALATE_AFTER_S
    escalation_channel: str = "ward-station"


@dataclass(frozen=True)
class LocatedSite:
    """A tissue site found on this frame's map: its peak and its place on the mat (mm)."""

    site: str
    x_mm: float
    y_mm: float
    peak_kpa: float


@dataclass(frozen=True)
class FrameAlerts:
    """What one frame brought: alarm and turn events, the posture, and each site's dose."""

    alarm_events: list[AlarmEvent]
    turn_events: list[TurnEvent]
    site_doses: dict[str, float] = field(default_factory=dict)
    posture: str | None = None


def technical_alarms(conditions) -> dict[str, str]:
    """A frame's technical conditions (``part``, ``message``) as the pipeline's technical alarm keys."""
    return {f"technical:{c.part.replace(' ', ':')}": f"{c.part}: {c.message}" for c in conditions}


def _technical(technical: dict[str, str] | None) -> dict:
    return {key: (AlarmCondition(key, "technical", "medium", False, message), None)
            for key, message in (technical or {}).items()}


def default_classifier() -> Callable[[BodyView], PostureEstimate]:
    """The shipped posture model's estimate of a view."""
    from appliance.alerts.posture import default_posture_model

    return default_posture_model().classify


def default_locator() -> Callable[[BodyView, str], list]:
    from appliance.alerts.sites import locate_sites

    return locate_sites


class AlertPipeline:
    """Posture, sites, dose, turns and alarms for one mat's pixel grid, for the patient in the bed.

    ``classify`` (view -> :class:`~appliance.alerts.posture.PostureEstimate`) and ``locate`` (view, posture ->
    site readings) default to the shipped posture model and site locator. An estimate that is not sure of its
    group leaves the patient in the last sure lying posture: no turn is counted and no site renamed on a map the
    model cannot tell (``posture_sure`` says so).
    """

    def __init__(self, grid: PixelGrid, settings: AlertSettings = AlertSettings(), *,
                 classify: Callable[[BodyView], PostureEstimate] | None = None,
                 locate: Callable[[BodyView, str], list] | None = None):
        self.grid, self.settings = grid, settings
        self.bed = is_bed(grid)
        self.curve: ToleranceCurve
        if settings.curve_points:
            self.curve = custom_curve(settings.curve_points, name=settings.curve, floor_kpa=settings.threshold_kpa)
        else:
            self.curve = tolerance_curve(settings.curve, floor_kpa=settings.threshold_kpa)
        self._classify = classify or (default_classifier() if self.bed else None)
        self._locate = locate or (default_locator() if self.bed else None)
        self._start_patient(None)
        self.engine = AlarmEngine()
        self.last_time_s: float | None = None
        self.clinical: dict[str, tuple[AlarmCondition, str | None]] = {}   # the last map's clinical conditions

    def _start_patient(self, episode: Episode | None) -> None:
        """Fresh doses, turn clock and regions for ``episode`` (None: an unnamed patient)."""
        s = self.settings
        self.episode = episode
        self.dose = SiteDose((*SITES, UNIDENTIFIED_SITE) if self.bed else (SMALL_MAT_SITE,), self.curve,
                             recovery=s.recovery,
                             relief_s=s.relief_s)
        self.turns = TurnClock(interval_s=s.turn_interval_s, grace_s=s.turn_grace_s, repeat_s=s.reminder_repeat_s,
                               at_risk_kpa=s.threshold_kpa, away_s=s.relief_s, hold_s=s.relief_s)
        self.regions = RegionTracker(self.grid, threshold_kpa=s.threshold_kpa)
        self.tracked: list = []                                  # the last map's regions, each named by its site
        self.posture: str | None = None                          # the last map's posture (held while unsure)
        self.posture_sure = True                                 # whether the model was sure of it
        self.sites: list[LocatedSite] = []                       # the last map's located sites
        self.places: dict[str, tuple[float, float]] = {}         # where each site was last found, mm
        self.place_groups: dict[str, str] = {}                   # and in which posture group
        self.held: set[str] = set()                              # sites whose alarm outlives a settings change
        self.named_kpa: dict[str, float] = {}                    # each site's peak when last named, kPa

    # --- frames ----------------------------------------------------------

    def update(self, pressure_map: PressureMap, technical: dict[str, str] | None = None) -> FrameAlerts:
        """One frame; ``technical`` maps a technical condition's key (``"technical:electrode:5"``) to its
        message while it holds."""
        now = pressure_map.time_s
        posture, located = self._read_body(pressure_map)
        peaks = {**self._where_sites_lay(pressure_map, posture, located), **{s.site: s.peak_kpa for s in located}}
        if self.last_time_s is not None and now > self.last_time_s:
            gap = min(now - self.last_time_s, MAX_COUNTED_GAP_S)
            while gap > 0:                          # a gap (a restart, a pause for maintenance) in steps
                step = min(gap, MAX_DT_S)
                self.dose.update(peaks, step)
                gap -= step
        self.last_time_s = now
        self.posture, self.sites = posture, located
        self.places.update({s.site: (s.x_mm, s.y_mm) for s in located})
        self.named_kpa.update({s.site: s.peak_kpa for s in located})
        if in_bed(posture):
            self.place_groups.update({s.site: posture_group(posture) for s in located})
        self.tracked = self._named_regions(pressure_map, located)
        doses = self.dose.doses()
        alarmed = frozenset(key.split(":", 1)[1] for key in self.clinical if key.startswith("pressure:"))
        turn_events = self.turns.update(now, posture, peaks, alarmed) if self.bed and posture is not None else []
        active = {}
        for site, dose in doses.items():
            if dose >= self.settings.alarm_dose:
                condition = self._pressure_condition(site)
                active[condition.key] = (condition, f"{dose:.2f} of the tolerance used")
        active.update(self._held_conditions(active))
        active.update(self._turn_conditions(now))
        active.update(self._bed_exit_condition(now))
        self.clinical = dict(active)
        return FrameAlerts(self.engine.assess(now, {**active, **_technical(technical)}), turn_events,
                           doses, posture)

    def hold(self, now_s: float, technical: dict[str, str]) -> FrameAlerts:
        """A frame time with no map: technical alarms move on, clinical ones stay as the last map left them.

        Without a map nothing is known of the skin, so no clinical alarm may end
        for want of data; the dose of the gap is added with the next map.
        """
        return FrameAlerts(self.engine.assess(now_s, {**self.clinical, **_technical(technical)}), [],
                           self.dose.doses(), self.posture)

    def _read_body(self, pressure_map: PressureMap) -> tuple[str | None, list[LocatedSite]]:
        """The posture and the located sites, in mat millimetres; on a small mat, the mat's peak as one site."""
        kpa = np.nan_to_num(np.asarray(pressure_map.pressure_kpa, dtype=float))
        if not self.bed:
            if not kpa.size or kpa.max() <= 0:
                return None, []
            x, y = self.grid.centres_mm[int(np.argmax(kpa))]
            return None, [LocatedSite(SMALL_MAT_SITE, float(x), float(y), float(kpa.max()))]
        view = body_view(kpa, self.grid)
        assert self._classify is not None and self._locate is not None     # a bed has both
        posture = self._sure_posture(self._classify(view))
        if posture == "out-of-bed":
            if kpa.max() < self.settings.threshold_kpa:
                return posture, []
            x, y = self.grid.centres_mm[int(np.argmax(kpa))]        # load, but no body to name it from
            return posture, [LocatedSite(UNIDENTIFIED_SITE, float(x), float(y), float(kpa.max()))]
        located = []
        for reading in self._locate(view, posture):
            if reading.site is None:
                continue
            x, y = view.mat_mm(reading.along_mm, reading.across_mm)
            located.append(LocatedSite(reading.site, float(x), float(y), float(reading.peak_kpa)))
        return posture, located

    def _where_sites_lay(self, pressure_map: PressureMap, posture: str | None, located: list[LocatedSite]) -> dict:
        """For the sites named in the posture group the patient still lies in and not named on this map: the load
        within ``FOLLOW_MM`` of where each last lay if it was loaded when last named, else its peak then."""
        group = posture_group(posture) if in_bed(posture) else None
        named = {s.site for s in located}
        kpa = np.nan_to_num(np.asarray(pressure_map.pressure_kpa, dtype=float)).ravel()
        out = {}
        for site, (x, y) in self.places.items():
            if site in named or group is None or self.place_groups.get(site) != group:
                continue
            named_kpa = self.named_kpa.get(site, math.inf)
            if named_kpa < self.settings.threshold_kpa:
                out[site] = named_kpa
                continue
            near = np.hypot(self.grid.centres_mm[:, 0] - x, self.grid.centres_mm[:, 1] - y) <= FOLLOW_MM
            out[site] = float(kpa[near].max()) if near.any() else 0.0
        return out

    def _sure_posture(self, estimate: PostureEstimate) -> str:
        """The estimate's posture when the model is sure of its group; otherwise the last lying posture, held
        until a sure estimate says the patient has moved."""
        self.posture_sure = estimate.sure
        return estimate.posture if estimate.sure or not in_bed(self.posture) else self.posture

    def _named_regions(self, pressure_map: PressureMap, located: list[LocatedSite]) -> list:
        """This frame's tracked regions, each named by the most loaded site inside it (None where none is)."""
        tracked = self.regions.update(pressure_map)
        w, h = self.grid.pixel_mm
        named = []
        for region in tracked:
            inside = [s for s in located
                      if region.mask[min(int(s.y_mm // h), self.grid.rows - 1),
                                     min(int(s.x_mm // w), self.grid.cols - 1)]]
            site = max(inside, key=lambda s: s.peak_kpa).site if inside else None
            named.append(dataclasses.replace(region, zone=site))
        return named

    # --- conditions ------------------------------------------------------

    def _pressure_condition(self, site: str) -> AlarmCondition:
        s = self.settings
        return AlarmCondition(f"pressure:{site}", "clinical", "medium", False,
                              f"sustained pressure at the {site_words(site)}: reposition the patient",
                              (Escalation(s.escalate_after_s, s.escalation_channel),))

    def hold_open_alarms(self) -> None:
        """Keep each site's open pressure alarm until the site has been relieved for the relief time, whatever
        the dose says now: called when the settings or the pressure calibration change, so that no alarm ends
        because the rules or the scale it was measured by did, only because the tissue was offloaded."""
        self.held |= {alarm.key.split(":", 1)[1] for alarm in self.engine.alarms("clinical")
                      if alarm.key.startswith("pressure:")}

    def _held_conditions(self, active: dict) -> dict:
        """The held sites' alarms still owed (a site stays held until relieved for the relief time)."""
        relieved = self.dose.relieved_s()
        self.held = {site for site in self.held if relieved.get(site, 0.0) < self.settings.relief_s}
        out = {}
        for site in sorted(self.held):
            condition = self._pressure_condition(site)
            if condition.key not in active:
                out[condition.key] = (condition, "held since the settings or calibration changed: relieve the site "
                                                 f"for {self.settings.relief_s / 60:g} min")
        return out

    def _turn_conditions(self, now_s: float) -> dict:
        owed = self.turns.reminder(now_s) if self.bed else None
        if owed is None:
            return {}
        level, number = owed
        due_in_s = self.turns.due_in_s(now_s)
        assert due_in_s is not None             # a turn is owed only once the clock runs
        late = max(0.0, -due_in_s) / 60
        if level == "due":
            condition = AlarmCondition("turn:due", "clinical", "medium", False, "repositioning is due")
        else:
            condition = AlarmCondition(f"turn:overdue:{number}", "clinical", "high", False,
                                       "repositioning is overdue",
                                       (Escalation(OVERDUE_ESCALATE_S, self.settings.escalation_channel),))
        return {condition.key: (condition, f"{late:.0f} min since due")}

    def _bed_exit_condition(self, now_s: float) -> dict:
        episode, turns = self.episode, self.turns
        if not (self.bed and episode is not None and episode.bed_exit_alert and turns.posture == "out-of-bed"
                and turns.away_since is not None and now_s - turns.away_since >= episode.bed_exit_after_s):
            return {}
        condition = AlarmCondition("bed-exit", "clinical", "medium", True, "the patient has left the bed")
        return {condition.key: (condition, f"away {(now_s - turns.away_since) / 60:.0f} min")}

    # --- what a nurse does -----------------------------------------------

    def record_turn(self, now_s: float, user: str) -> list[TurnEvent]:
        """A turn done by hand and recorded by ``user``: the clock restarts now."""
        alarmed = frozenset(key.split(":", 1)[1] for key in self.clinical if key.startswith("pressure:"))
        events = self.turns.record(now_s, user, {s.site: s.peak_kpa for s in self.sites}, alarmed)
        self.clinical = {k: v for k, v in self.clinical.items() if not k.startswith("turn:")}
        return events

    def admit(self, now_s: float, episode: Episode) -> list[Event]:
        """A new patient in the bed: the last one is discharged (their clinical alarms end), and doses and the
        turn clock start afresh. The records say who was admitted and discharged, by whom."""
        records = self.discharge(now_s, episode.admitted_by) if self.episode is not None else \
            [self.record(e) for e in self.engine.end_category(now_s, "clinical", episode.admitted_by)]
        self._start_patient(episode)
        self.clinical = {}
        words = ", ".join(x for x in (episode.name, None if episode.braden is None else f"Braden {episode.braden}",
                                      "bed-exit alert on" if episode.bed_exit_alert else None) if x)
        return records + [Event(now_s, "episode", "admitted", message=f"admitted {episode.patient_id}"
                                + (f" ({words})" if words else ""), user=episode.admitted_by,
                                patient=episode.patient_id)]

    def discharge(self, now_s: float, user: str) -> list[Event]:
        """The patient leaves: their clinical alarms end; the bed carries on for an unnamed patient."""
        if self.episode is None:
            raise ConfigError("no patient is admitted to this bed")
        records = [self.record(e) for e in self.engine.end_category(now_s, "clinical", user)]
        records.append(Event(now_s, "episode", "discharged", message=f"discharged {self.episode.patient_id}",
                             user=user, patient=self.episode.patient_id))
        self._start_patient(None)
        self.clinical = {}
        return records

    # --- records ---------------------------------------------------------

    def record(self, event: AlarmEvent | TurnEvent) -> Event:
        """The record of an event, with its site's place on the mat, the posture and the patient."""
        record = as_event(event)
        site = record.site
        place = self.places.get(site) if site else None
        return dataclasses.replace(record, posture=record.posture or self.turns.posture or self.posture,
                                   x_mm=None if place is None else round(place[0], 1),
                                   y_mm=None if place is None else round(place[1], 1),
                                   patient=None if self.episode is None else self.episode.patient_id)

    # --- persistence -----------------------------------------------------

    def state(self) -> dict:
        """Everything needed to carry on after a restart, as plain JSON types."""
        return {"regions": self.regions.state(), "dose": self.dose.state(), "turns": self.turns.state(),
                "alarms": self.engine.state(), "last_time_s": self.last_time_s, "posture": self.posture,
                "places": {site: list(xy) for site, xy in self.places.items()}, "place_groups": self.place_groups,
                "named_kpa": self.named_kpa,
                "episode": None if self.episode is None else self.episode.to_dict(),
                "clinical": [[c.to_dict(), detail] for c, detail in self.clinical.values()],
                "held": sorted(self.held), "settings": settings_record(self.settings)}

    @classmethod
    def from_state(cls, grid: PixelGrid, state: dict, settings: AlertSettings = AlertSettings(),
                   **body) -> AlertPipeline:
        """The pipeline :meth:`state` saved, continued under ``settings``.

        Patient settings changed since (by a nurse, or in the configuration while
        the monitor was down) apply from now on: the doses take the new curve,
        recovery and relief, and each site's dose, the share of its tolerance
        already used, carries over unchanged. An open pressure alarm is held
        (:meth:`hold_open_alarms`) when the settings differ from those saved: a
        new threshold or alarm dose must not end it.
        """
        pipeline = cls(grid, settings, **body)
        episode = state.get("episode")
        pipeline._start_patient(None if episode is None else Episode.from_dict(episode))
        pipeline.regions = RegionTracker.from_state(grid, state["regions"], threshold_kpa=settings.threshold_kpa)
        pipeline.dose = SiteDose.from_state(state["dose"], pipeline.curve, recovery=settings.recovery,
                                            relief_s=settings.relief_s)
        pipeline.turns.restore(state["turns"])
        pipeline.engine = AlarmEngine.from_state(state["alarms"])
        pipeline.last_time_s = state["last_time_s"]
        pipeline.posture = state.get("posture")
        pipeline.places = {site: (float(x), float(y)) for site, (x, y) in (state.get("places") or {}).items()}
        pipeline.place_groups = {str(site): str(group) for site, group in (state.get("place_groups") or {}).items()}
        pipeline.named_kpa = {str(site): float(kpa) for site, kpa in (state.get("named_kpa") or {}).items()}
        pipeline.clinical = {c["key"]: (AlarmCondition.from_dict(c), detail) for c, detail in state.get("clinical", [])}
        pipeline.held = {str(site) for site in state.get("held", [])}
        if state.get("settings") is not None and state["settings"] != settings_record(settings):
            pipeline.hold_open_alarms()
        return pipeline


def settings_record(settings: AlertSettings) -> dict:
    """``settings`` as plain JSON types, saved with the state to tell whether they changed since."""
    record = dataclasses.asdict(settings)
    record["curve_points"] = None if settings.curve_points is None else [list(p) for p in settings.curve_points]
    return record
