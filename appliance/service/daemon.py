"""The monitor daemon: acquire -> pressure map -> alerts -> store -> notifiers and live view, frame by frame.

One loop owns every stage, in the order the data flows, so a frame's alarm
events are committed with the alert state they led to before anyone is told:
after a crash or power cut the daemon resumes from the store (the alert state,
the empty-mat reference, and on the virtual bed the scene time) and neither
loses nor repeats an alarm. The last frame's events are kept with the state and
notified again after a restart, so a crash between the commit and the hand-over
to the notifiers loses no notification (delivery is at least once). Nothing downstream can hold the loop up: notifiers
and the live view take their work on their own threads. Each frame the notifiers also get a compact summary of
the live view (:func:`ward_summary`) for the ward station; sending it never waits either.

Frames that cannot be taken are technical conditions, not silence: the front
end's error at once (``technical:front-end``), and after ``NO_DATA_FRAMES`` in a
row ``technical:no-data``; during a gap clinical alarms stay as the last map
left them. Commands from outside (acknowledge, pause audio) are queued in the
store by whoever asks (the web screen is another process), applied at the start
of the next frame, and marked done in the commit of the events they caused, so
each is applied exactly once even across a crash. The ward station's commands
come through the ward link instead, as often as the network repeats them: each
is applied once under the station's id, kept in the store with the frame that
applied it, and a repeat is answered as the first was and applies nothing.

Faults around the loop are technical alarms too, never its end: a full or
failing disk (the store's writes held in memory, :mod:`appliance.store.holding`),
a helper thread that fails (restarted by its supervisor), and a saved state that
cannot be continued.

Under systemd (``Type=notify``) it reports ready once the first map is made,
pings the watchdog every frame, and on SIGTERM finishes the frame, flushes the
notifiers, closes the store and exits 0.
"""

from __future__ import annotations

import contextlib
import logging
import sqlite3
import threading
import time
from collections.abc import Callable

import numpy as np

from appliance.alerts.anatomy import POSTURE_WORDS, site_words
from appliance.alerts.episodes import Episode
from appliance.alerts.events import Event
from appliance.alerts.limits import not_default
from appliance.alerts.nurse_call import NurseCallRelays
from appliance.alerts.ward_commands import WardCommand
from appliance.alerts.wardlink import WardLink
from appliance.alerts.pipeline import AlertPipeline, FrameAlerts, technical_alarms
from appliance.charting.link import ChartingLink
from appliance.core.pressure import KPA_PER_MMHG
from appliance.errors import ApplianceError, ConfigError, DataFileInvalid, ReconstructionError, StoreCorrupt
from appliance.service.config_sections import MonitorConfig
from appliance.service.live import LiveChannel, map_mmhg
from appliance.service.monitor import Monitor, reference_state
from appliance.service.systemd import SystemdNotifier
from appliance.store.holding import HeldWrites

log = logging.getLogger(__name__)

CommandHandler = Callable[[float, dict, str, int], tuple[list[Event], str]]
"""``handler(now, args, user, command_id) -> (events, result)``; raising refuses the command with the reason."""

NO_DATA_FRAMES = 3
"""Frames in a row without a map before ``technical:no-data`` is raised (within the 3 frames an
electrode fault must be reported in)."""
PRUNE_EVERY_S = 3600.0
"""How often (monitoring time) the store drops history and events past their retention or its size cap."""


def ward_summary(snapshot: dict) -> dict:
    """The live snapshot cut down for the ward station: no map (too big for a ward of beds), no positions.

    Between maps (a fault) ``peak_mmhg`` is None and ``regions`` empty.
    """
    pressure_map = snapshot.get("map")
    return {"bed_id": snapshot["bed_id"], "time_s": snapshot["time_s"],
            "peak_mmhg": None if pressure_map is None else pressure_map["peak_kpa"] / KPA_PER_MMHG,
            "regions": [{"zone": r["zone"], "words": r.get("words"), "peak_mmhg": r["peak_mmhg"], "dose": r["dose"]}
                        for r in snapshot.get("regions", [])],
            "posture": snapshot.get("posture"), "patient": snapshot.get("patient"),
            "turn": {"due_in_s": snapshot["turn"]["due_in_s"]},
            "alarms": [{k: a[k] for k in ("alarm_id", "key", "priority", "state", "message", "acknowledged_by")}
                       for a in snapshot["alarms"]],
            "status": {"maps": snapshot["status"]["maps"], "faults": snapshot["status"]["faults"],
                       "source": snapshot["status"].get("source")}}


class MonitorDaemon:
    """The monitor configured by ``config``, around a frame ``source`` (a VirtualBedSource or a BoardSource).

    ``on_event`` gets each :class:`Event` after it is committed; ``on_map``
    each pressure map; ``say`` the daemon's progress lines.
    """

    def __init__(self, config: MonitorConfig, source, model, calibration, store, *, notifiers=(), gpio=None,
                 nurse_call: NurseCallRelays | None = None, live: LiveChannel | None = None,
                 on_event: Callable[[Event], None] | None = None, on_map: Callable | None = None,
                 say: Callable[[str], None] = log.info,
                 systemd: SystemdNotifier | None = None, lock=None):
        self.lock = lock            # the data folder's, given up last on close
        self.config, self.source, self.model, self.store = config, source, model, store
        self.writes = HeldWrites(store)         # a full disk holds the records in memory; monitoring goes on
        self.notifiers, self.gpio, self.nurse_call, self.live = list(notifiers), gpio, nurse_call, live
        self.ward_link = next((n for n in self.notifiers if isinstance(n, WardLink)), None)
        self.on_event, self.on_map, self.say = on_event, on_map, say
        self.systemd = systemd or SystemdNotifier()
        self.monitor = Monitor(source.acquire, model, calibration,   # refuses a calibration for another mat
                               adaptive=getattr(source, "adaptive", False))
        self.grid = model.reconstructor.grid
        self.pipeline = AlertPipeline(self.grid, config.alerts)
        self.stop_requested = threading.Event()
        self.maps = self.faults = self.consecutive_faults = 0
        self.last_fault: str | None = None
        self.resumed_from_s: float | None = None
        self.last_prune_s: float | None = None
        self.start_faults: dict[str, tuple[str, float]] = {}   # technical alarm key -> (message, shown until)
        self._ready = False
        self.commands: dict[str, CommandHandler] = {"acknowledge": self._acknowledge,
                                                     "pause-audio": self._pause_audio,
                                                     "record-turn": self._record_turn,
                                                     "admit": self._admit, "discharge": self._discharge}

    def add_commands(self, handlers: dict[str, CommandHandler]) -> None:
        """More commands the queue may carry (settings, engineering), by kind."""
        clash = handlers.keys() & self.commands.keys()
        if clash:
            raise ValueError(f"commands {sorted(clash)} are already handled")
        self.commands.update(handlers)

    def progress(self, command_id: int) -> Callable[[float, str], None]:
        """A progress callback for a long command: records the share done for screens and keeps the systemd
        watchdog fed, since the loop is busy but alive."""
        def report(share: float, note: str = "") -> None:
            with contextlib.suppress(sqlite3.OperationalError):   # only a progress bar: a full disk
                self.store.set_progress(command_id, share, note)    # shows as the storage alarm
            self.systemd.ping()
        return report

    # Start: resume or begin.

    def start(self) -> None:
        """Resume the reference and alert state from the store, or take a fresh reference and start clean."""
        try:
            state, reference = self.store.load_state("alerts"), self.store.load_state("reference")
        except StoreCorrupt as exc:
            self._lost_state(str(exc))
            state = reference = None
        if state is not None and reference is not None and self._restore(state, reference):
            return
        frame = self.source.reference()
        try:
            fit = self.monitor.take_reference(frame)
        except ReconstructionError as exc:          # kept, so every frame raises the technical alarm it earns
            self.monitor.reference = np.asarray(frame.volts, dtype=float)
            self.monitor.reference_temperature_c, fit = frame.temperature_c, None
            self.say(f"the empty-mat reference does not fit the model: {exc}")
        self.writes.save_state("reference", reference_state(self.model, frame, fit), 0.0)
        self.say("took the empty-mat reference" + ("" if fit is None else f"; fitted {fit.describe()}"))

    def _restore(self, state: dict, reference: dict) -> bool:
        volts = np.array([np.nan if v is None else v for v in reference.get("volts", [])], dtype=float)
        if reference.get("layout") != self.model.setup.layout.name or len(volts) != len(self.model.setup.protocol):
            self.say("the saved reference is for another mat: starting afresh")
            return False
        try:
            pipeline = AlertPipeline.from_state(self.grid, state, self.config.alerts)
        except (DataFileInvalid, ConfigError, KeyError, TypeError, ValueError) as exc:
            self._lost_state(f"the saved alert state in {self.store.path} cannot be continued ({exc})")
            return False
        try:
            self.monitor.set_reference(volts, reference.get("temperature_c"))    # the same fit as when it was taken
        except ReconstructionError as exc:
            self.say(f"the saved reference does not fit the model ({exc}): starting afresh")
            return False
        self.pipeline = pipeline
        if pipeline.last_time_s is not None:
            self.resumed_from_s = pipeline.last_time_s
            self.source.resume_after(pipeline.last_time_s)
        active = len(pipeline.engine.alarms())
        self.say(f"resumed from the store at {pipeline.last_time_s} s with {active} alarm(s) open")
        self._resend_last_frame()
        return True

    def _lost_state(self, why: str) -> None:
        """Start afresh without the saved doses, turn clock and open alarms, and say so with a technical alarm
        for one turn interval, by which time the turn clock is whole again: monitoring goes on, but a nurse
        must know that what the screen shows began now."""
        self.say(f"{why}: starting afresh")
        until = self.source.now() + self.config.alerts.turn_interval_s
        self.start_faults["technical:saved-state"] = (
            f"saved state lost ({why}): doses, the turn clock and open alarms started afresh", until)

    def _resend_last_frame(self) -> None:
        """Notify the last committed frame's events again: the crash may have come before they were handed
        over. The ward link's outbox knows an event it already numbered, and the webhook's receivers
        de-duplicate on (alarm_id, kind, time_s), so a repeat is harmless and a loss is not."""
        try:
            outbox = self.store.load_state("outbox") or {"events": []}
            events = [Event(**fields) for fields in outbox["events"]]
        except (StoreCorrupt, KeyError, TypeError) as exc:
            self.say(f"the last frame's events cannot be notified again: {exc}")
            return
        for event in events:
            for notifier in self.notifiers:
                notifier.notify(event)
        if events and self.notifiers:
            self.say(f"notified the last frame's {len(events)} event(s) again")

    # The loop.

    def run(self, frames: int | None = None) -> int:
        """Frames until ``frames`` were taken (maps or faults), the source ends, or a stop is requested."""
        done = 0
        while (frames is None or done < frames) and not self.stop_requested.is_set():
            if not self.source.wait_for_frame(self.stop_requested):
                break
            self.step()
            done += 1
        return done

    def request_stop(self, *_signal) -> None:
        """Finish the frame under way, then stop (the SIGTERM handler)."""
        self.stop_requested.set()

    def acknowledge(self, alarm_id: int, user: str) -> int:
        """Acknowledge an alarm at the next frame. From the loop's thread; another process (the web screen)
        queues the same command through its own connection to the store."""
        return self.store.queue_command("acknowledge", {"alarm_id": alarm_id}, user)

    def pause_audio(self, user: str, duration_s: float) -> int:
        return self.store.queue_command("pause-audio", {"duration_s": duration_s}, user)

    def step(self) -> FrameAlerts:
        """One frame through every stage."""
        now = self.source.now()
        events, outcomes = self._apply_commands(now)
        ward_events, ward_done = self._apply_ward_commands(now)
        events += ward_events
        try:
            pressure_map = self.monitor.next_map()
        except (ApplianceError, OSError) as exc:
            pressure_map = None
            self.faults += 1
            self.consecutive_faults += 1
            self.last_fault = f"{type(exc).__name__}: {exc}"
            self.say(f"FAULT ({self.consecutive_faults} in a row): {self.last_fault}")
        technical = technical_alarms(self.monitor.conditions)          # during a gap, as the last frame left them
        technical.update({key: message for key, (message, until) in self.start_faults.items() if now < until})
        technical.update(self._helper_faults())
        technical.update(self.writes.condition())
        if pressure_map is None:
            technical["technical:front-end"] = f"no frame from the front end: {self.last_fault}"
            if self.consecutive_faults >= NO_DATA_FRAMES:
                technical["technical:no-data"] = f"no pressure map for {self.consecutive_faults} frames"
            alerts = self.pipeline.hold(now, technical)
        else:
            self.consecutive_faults = 0
            self.maps += 1
            now = pressure_map.time_s
            alerts = self.pipeline.update(pressure_map, technical)
        events += [self.pipeline.record(e) for e in alerts.turn_events + alerts.alarm_events]
        snapshot = self._snapshot(now, pressure_map, alerts)
        if pressure_map is not None:
            self.writes.record_map(now, np.nan_to_num(pressure_map.pressure_kpa), snapshot["regions"])
        self.writes.commit_frame(now, events + self._clock_steps(now),
                                 {"alerts": self.pipeline.state(), "outbox": {"events": [e.to_dict() for e in events]}},
                                 outcomes, ward_done)
        if self.ward_link is not None:          # answered once kept: after a crash before this, from the store
            for done in ward_done:
                self.ward_link.answer(done["ward_id"], done["applied"], done["result"])
        self._tell(events, now)
        self._prune_when_due(now)
        if pressure_map is not None and self.on_map is not None:
            self.on_map(pressure_map)
        if self.live is not None:
            self.live.publish(snapshot)
        summary = ward_summary(snapshot)
        for notifier in self.notifiers:
            if hasattr(notifier, "summarise"):          # the ward link, and the charting link's observations
                notifier.summarise(summary)
        if not self._ready and pressure_map is not None:
            self._ready = True
            self.systemd.ready(f"monitoring {self.config.bed_id}")
        self.systemd.ping()
        return alerts

    def _apply_commands(self, now: float) -> tuple[list[Event], list[tuple[int, bool, str]]]:
        """The queued commands, each through its handler: their events, and each one's outcome."""
        events, outcomes = [], []
        held = self.writes.held_commands          # applied, their outcome not yet written
        for command in self.store.pending_commands():
            if command["id"] in held:
                continue
            kind, args, user = command["kind"], command["args"], command["user"]
            try:
                handler = self.commands.get(kind)
                if handler is None:
                    raise ValueError(f"unknown command {kind!r}")
                done, result = handler(now, args, user, command["id"])
            except (ApplianceError, OSError, sqlite3.OperationalError, ValueError, KeyError, TypeError) as exc:
                self.say(f"command {kind} by {user} refused: {exc}")
                outcomes.append((command["id"], False, str(exc)))
                continue
            events += done
            outcomes.append((command["id"], True, result))
        return events, outcomes

    def _apply_ward_commands(self, now: float) -> tuple[list[Event], list[dict]]:
        """The ward station's commands the link has taken: their events, and a record of each one applied or
        refused this frame for the store. A repeat of one already taken (kept in the store, held in memory
        while the disk refuses writes, or twice in this frame) is answered as it was the first time."""
        if self.ward_link is None:
            return [], []
        events: list[Event] = []
        taken: dict[str, dict] = {}
        for command in self.ward_link.take_commands():
            if command.id in taken:
                continue
            try:
                known = self.writes.held_ward_command(command.id) or self._stored_ward_command(command.id)
            except sqlite3.OperationalError as exc:    # cannot tell whether it was applied: the station asks again
                self.say(f"ward command {command.id} left for the station's next resend: {exc}")
                continue
            if known is not None:
                self.ward_link.answer(command.id, known["applied"], known["result"])
                continue
            done, applied, result = self._ward_command(now, command)
            events += done
            taken[command.id] = {"ward_id": command.id, "kind": command.kind, "args": command.args,
                                 "user": command.bed_user, "queued_at": command.issued_at, "applied": applied,
                                 "result": result}
        return events, list(taken.values())

    def _stored_ward_command(self, ward_id: str) -> dict | None:
        command = self.store.ward_command(ward_id)
        return None if command is None else {"applied": command["state"] == "done", "result": command["result"]}

    def _ward_command(self, now: float, command: WardCommand) -> tuple[list[Event], bool, str]:
        """One new command from the ward station through its handler, unless it came too late."""
        late_s = time.time() - command.expires_at
        if late_s > 0:
            result = f"expired: {command.kind} from {command.bed_user} came {late_s:.0f} s after it expired " \
                     f"(the bed was away or the network slow); nothing was done, ask again if still needed"
            self.say(f"ward command {command.kind} by {command.bed_user} refused: {result}")
            return [], False, result
        try:
            done, result = self.commands[command.kind](now, command.args, command.bed_user, 0)
        except (ApplianceError, ValueError, KeyError, TypeError) as exc:
            self.say(f"ward command {command.kind} by {command.bed_user} refused: {exc}")
            return [], False, str(exc)
        return done, True, result

    def _acknowledge(self, now: float, args: dict, user: str, _id: int) -> tuple[list[Event], str]:
        done = [self.pipeline.record(e) for e in self.pipeline.engine.acknowledge(now, int(args["alarm_id"]), user)]
        return done, f"{len(done)} event(s)"

    def _pause_audio(self, now: float, args: dict, user: str, _id: int) -> tuple[list[Event], str]:
        alarm_id = None if args.get("alarm_id") is None else int(args["alarm_id"])       # None: every alarm
        done = [self.pipeline.record(e)
                for e in self.pipeline.engine.pause_audio(now, user, float(args["duration_s"]), alarm_id)]
        return done, f"{len(done)} event(s)"

    def _record_turn(self, now: float, args: dict, user: str, _id: int) -> tuple[list[Event], str]:
        """A turn done by hand: by ``user``, or by the nurse named in ``args["by"]`` when another enters it."""
        done = [self.pipeline.record(e) for e in self.pipeline.record_turn(now, str(args.get("by") or user))]
        return done, "turn recorded"

    def _admit(self, now: float, args: dict, user: str, _id: int) -> tuple[list[Event], str]:
        """A new patient: the last one's episode closes, and doses and the turn clock start afresh."""
        # The command's arguments come unchecked: Episode refuses any that is not what it says.
        episode = Episode(patient_id=args.get("patient_id"),  # type: ignore[arg-type]
                          admitted_s=now, admitted_by=user, name=args.get("name"),
                          braden=args.get("braden"), bed_exit_alert=bool(args.get("bed_exit_alert", False)),
                          **({"bed_exit_after_s": args["bed_exit_after_s"]} if "bed_exit_after_s" in args else {}))
        return self.pipeline.admit(now, episode), f"admitted {episode.patient_id}"

    def _discharge(self, now: float, args: dict, user: str, _id: int) -> tuple[list[Event], str]:
        done = self.pipeline.discharge(now, user)
        return done, f"discharged {done[-1].patient}"

    def _tell(self, events: list[Event], now: float) -> None:
        for event in events:
            for notifier in self.notifiers:
                notifier.notify(event)
            if self.on_event is not None:
                self.on_event(event)
        if self.gpio is not None:
            self.gpio.show(self.pipeline.engine.audible(now))
        if self.nurse_call is not None:
            self.nurse_call.show(self.pipeline.engine.alarms())

    def _prune_when_due(self, now: float) -> None:
        """Retention: at the first frame and every ``PRUNE_EVERY_S`` after (a clock step counts as due), so the
        store keeps to its ages and size cap however long the bed runs. A disk that refuses is the storage alarm's
        business; the next attempt comes an interval later."""
        if self.last_prune_s is not None and abs(now - self.last_prune_s) < PRUNE_EVERY_S:
            return
        self.last_prune_s = now
        try:
            deleted = self.store.prune(now)
        except (sqlite3.OperationalError, OSError) as exc:
            self.say(f"the store's retention could not run: {exc}")
            return
        if any(deleted.values()):
            self.say(f"retention: {deleted['history']} map(s) and {deleted['events']} event(s) past their keeping "
                     f"dropped from the store")

    def _clock_steps(self, now: float) -> list[Event]:
        """A wall-clock step since the last frame, as a record for the log (not a notification: the frame
        times, kept on the monotonic clock, did not step)."""
        step = getattr(self.source, "clock_step", lambda: None)()
        if step is None:
            return []
        message = f"the wall clock stepped {'forward' if step > 0 else 'back'} {abs(step):.0f} s; frame times " \
                  f"carry on from the monotonic clock"
        self.say(message)
        return [Event(now, "clock", "clock-step", message=message)]

    def _helper_faults(self) -> dict[str, str]:
        """A technical alarm for each helper that is failing: the live view's writer, a notifier's threads
        (restarted with a back-off by their supervisors), the nurse-call relays' lines."""
        faults = {}
        if self.live is not None and self.live.fault is not None:
            faults["technical:live-view"] = f"the live view cannot be written (retrying): {self.live.fault}"
        for notifier in self.notifiers:
            if (fault := getattr(notifier, "fault", None)) is not None:
                faults[f"technical:notifier:{notifier.name}"] = f"the {notifier.name} notifier is failing " \
                                                                 f"(restarting): {fault}"
        for notifier in self.notifiers:
            if hasattr(notifier, "conditions"):         # the ward link's and the charting link's own alarms
                faults.update(notifier.conditions())
        if self.nurse_call is not None:
            faults.update(self.nurse_call.conditions())
        return faults

    def _snapshot(self, now: float, pressure_map, alerts: FrameAlerts) -> dict:
        """What the live view shows: the map, regions with their dose, the turn clock, alarms and status."""
        engine, turns = self.pipeline.engine, self.pipeline.turns
        snapshot = {
            "bed_id": self.config.bed_id, "time_zone": self.config.time_zone, "time_s": now,
            "sequence": self.maps + self.faults,
            "frame_interval_s": self.config.frame_interval_s, "wall_interval_s": self.source.pace.period_s,
            "status": {"maps": self.maps, "faults": self.faults, "consecutive_faults": self.consecutive_faults,
                       "last_fault": self.last_fault, "source": self.config.source},
            "turn": {"last_turn_s": turns.last_turn_s, "due_in_s": turns.due_in_s(now), "bed_empty": turns.bed_empty,
                     "interval_s": turns.interval_s, "turning_since_s": turns.turning_since},
            "posture": self.pipeline.posture,
            "posture_words": POSTURE_WORDS.get(self.pipeline.posture or ""),
            "posture_sure": self.pipeline.posture_sure,
            "patient": None if self.pipeline.episode is None else
            {k: getattr(self.pipeline.episode, k) for k in ("patient_id", "name", "braden", "bed_exit_alert")},
            "sites": [{"site": s.site, "words": site_words(s.site),
                       "x_mm": s.x_mm, "y_mm": s.y_mm, "peak_mmhg": s.peak_kpa / KPA_PER_MMHG,
                       "dose": alerts.site_doses.get(s.site)} for s in self.pipeline.sites],
            "alarms": [{"alarm_id": a.alarm_id, "key": a.key, "category": a.category, "priority": a.priority,
                        "state": a.state, "message": a.message, "raised_s": a.raised_s,
                        "acknowledged_by": a.acknowledged_by,
                        "audio_paused": a.audio_paused_until is not None and a.audio_paused_until > now,
                        "delivery": None if self.ward_link is None else self.ward_link.delivery(a.alarm_id)}
                       for a in engine.alarms()],
            "ward_link": None if self.ward_link is None else self.ward_link.status(),
            "charting": next((n.status() for n in self.notifiers if isinstance(n, ChartingLink)), None),
            "audible": engine.audible(now),
            "settings_changed": not_default(self.pipeline.settings),   # on screen while any is not the default
        }
        if pressure_map is not None:
            g = self.grid
            snapshot["map"] = {"mmhg": map_mmhg(pressure_map.pressure_kpa), "pixel_mm": list(g.pixel_mm),
                               "peak_kpa": pressure_map.peak_kpa, "usable_readings": pressure_map.usable_readings}
            snapshot["regions"] = [{"id": r.id, "zone": r.zone, "words": r.zone and site_words(r.zone),
                                    "peak_mmhg": r.peak_kpa / KPA_PER_MMHG, "area_cm2": r.area_cm2,
                                    "x_mm": r.x_mm, "y_mm": r.y_mm, "since_s": r.first_seen_s,
                                    "dose": alerts.site_doses.get(r.zone) if r.zone else None}
                                   for r in self.pipeline.tracked]
        return snapshot

    def close(self) -> None:
        """Tell systemd, deliver what the notifiers hold, write the last live view, close the store."""
        self.systemd.stopping()
        for notifier in self.notifiers:
            notifier.close()
        if self.gpio is not None:
            self.gpio.close()
        if self.nurse_call is not None:
            self.nurse_call.close()
        if self.live is not None:
            self.live.close()
        if not self.writes.flush():
            self.say(f"the store still refuses writes ({self.writes.failure}): {self.writes.held} record(s) held "
                     f"in memory are lost")
        try:
            self.store.close()
        except sqlite3.OperationalError as exc:
            self.say(f"the store could not be closed cleanly ({exc}); it recovers its journal at the next start")
        if self.lock is not None:
            self.lock.release()

