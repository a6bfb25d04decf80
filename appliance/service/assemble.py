"""Build the monitor daemon a configuration describes: model, frame source, calibration, store, notifiers.

The one place that knows how the parts fit, as an app factory does, so the
``run`` and ``sim run`` commands and the tests start the same monitor.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

from appliance.service.config_sections import MonitorConfig
from appliance.service.daemon import MonitorDaemon
from appliance.service.live import LiveChannel
from appliance.service.starting import StartingReport

LIVE_FILE = "live.json"
STORE_FILE = "appliance.db"
DEAD_LETTER_FILE = "dead-letters.jsonl"
OUTBOX_FILE = "ward-outbox.db"


def assemble(config: MonitorConfig, *, say: Callable[[str], None], on_event=None, on_map=None,
             live: bool = True) -> MonitorDaemon:
    """The daemon, started (reference taken or state resumed) and ready to ``run``."""
    from appliance.service.datalock import lock_data_dir
    from appliance.service.config_sections import default_data_dir

    data_dir = Path(config.data_dir or default_data_dir())
    data_dir.mkdir(parents=True, exist_ok=True)
    lock = lock_data_dir(data_dir)          # before anything in the folder is read or written
    try:
        return _assemble(dataclasses.replace(config, data_dir=data_dir), lock, say=say, on_event=on_event,
                         on_map=on_map, live=live)
    except BaseException:
        lock.release()
        raise


def _assemble(config: MonitorConfig, lock, *, say, on_event, on_map, live: bool) -> MonitorDaemon:
    from appliance.charting.link import ChartingLink
    from appliance.service.charting_target import follow_patient
    from appliance.core.model_cache import cached_model, default_cache_dir, default_setup
    from appliance.core.named_layouts import get_layout
    from appliance.service import settings
    from appliance.service.engineering import engineering_commands
    from appliance.store import Store

    data_dir = config.data_dir
    assert data_dir is not None                 # assemble() sets it
    config = settings.load_overlaid(config, data_dir)   # the screen's settings
    layout = get_layout(config.layout)
    setup = default_setup(layout)
    protocol = setup.protocol
    channel = LiveChannel(data_dir / LIVE_FILE) if live else None   # the screen shows the start-up on it
    starting = StartingReport(channel, say)
    closers = [channel.close] if channel is not None else []
    try:
        model, _ = cached_model(setup, config.cache_dir or default_cache_dir(),
                                lambda step, share: starting("model", share, step))
        source = _source(config, layout, protocol)
    except BaseException:
        starting.failed()
        for close in closers:
            close()
        raise
    if hasattr(source, "close"):
        closers.append(source.close)
    try:
        calibration = _calibration(config, source, model, config.cache_dir or default_cache_dir(), say, starting)
        store = Store.open(data_dir / STORE_FILE, history_interval_s=config.store.history_interval_s,
                           history_days=config.store.history_days, event_days=config.store.event_days,
                           max_bytes=int(config.store.max_mb * 1024 * 1024), check=True)
        closers.append(store.close)
        notifiers = _notifiers(config, data_dir, closers)
        daemon = MonitorDaemon(config, source, model, calibration, store, notifiers=notifiers,
                               gpio=_gpio(config, source), nurse_call=_nurse_call(config, source), live=channel,
                               on_event=on_event, on_map=on_map, say=say, lock=lock)
        settings.attach(daemon)
        for notifier in notifiers:
            if isinstance(notifier, ChartingLink):  # it names the admitted patient in its messages
                follow_patient(notifier, daemon)
        daemon.add_commands(engineering_commands(daemon))
        starting("reference", 0.0)
        daemon.start()
    except BaseException:
        starting.failed()
        for close in reversed(closers):
            close()
        raise
    return daemon


def _source(config: MonitorConfig, layout, protocol):
    if config.source == "virtual":
        from appliance.service.virtual_bed import VirtualBedSource
        from appliance.sim.scenes import load_scene

        return VirtualBedSource(layout, load_scene(config.scenario), protocol, seed=config.seed,
                                frame_interval_s=config.frame_interval_s, speed=config.speed)
    from appliance.service.board_source import BoardSource

    return BoardSource(config.board, layout, protocol, frame_interval_s=config.frame_interval_s, seed=config.seed)


def _calibration(config: MonitorConfig, source, model, cache_dir: Path, say, starting: StartingReport):
    """The configured calibration; on the virtual bed, its own: made once and kept with the built models,
    since like them it follows from the simulated mat alone."""
    from appliance.core.pressure import check_plausible, load_pressure_calibration
    from appliance.errors import ConfigError

    starting("calibration", 0.0)
    if config.calibration is not None:
        calibration = load_pressure_calibration(config.calibration)
        check_plausible(calibration, f"[monitor] calibration {config.calibration}")
        return calibration
    if config.source != "virtual":
        raise ConfigError("[monitor] calibration is needed with a board: make one with `appliance calibrate "
                          "pressure --source hardware`")
    path = virtual_calibration_path(cache_dir, model)
    calibration, made = source.calibration(
        model, path, progress=lambda k, n, load: starting("calibration", k / n, f"virtual mat load {k}/{n}")
        if k % 10 == 1 else None)
    say(f"pressure calibration {'made and saved to' if made else 'loaded from'} {path}")
    return calibration


def virtual_calibration_path(cache_dir: Path, model) -> Path:
    """Where the virtual mat's calibration is kept: one per layout and algorithm, and apart for a model fitted to
    its references, whose images (and so curve) differ from the nominal model's."""
    fitted = "-fitted" if model.setup.contact_fit_mode == "relinearise" else ""
    return Path(cache_dir) / f"virtual-pressure-{model.setup.layout.name}-{model.setup.options.algorithm}{fitted}.json"


def _notifiers(config: MonitorConfig, data_dir: Path, closers: list) -> list:
    """The ward link (with its outbox), the webhook and the charting link (with its queue), each added to
    ``closers`` as soon as it is made."""
    from appliance.alerts.notifiers import WebhookNotifier
    from appliance.alerts.wardlink import WardLink
    from appliance.charting.link import ChartingLink
    from appliance.service.charting_target import charting_link

    notifiers: list[WardLink | WebhookNotifier | ChartingLink] = []
    if config.mqtt is not None or config.engine is not None:
        link = _ward_link(config, data_dir)
        notifiers.append(link)
        closers.append(link.close)                  # closes the outbox too
    if config.webhook is not None:
        notifiers.append(WebhookNotifier(config.webhook.url, timeout_s=config.webhook.timeout_s,
                                         dead_letter_path=data_dir / DEAD_LETTER_FILE))
        closers.append(notifiers[-1].close)
    charting = charting_link(config, data_dir)
    if charting is not None:
        notifiers.append(charting)
        closers.append(charting.close)              # closes the queue too
    return notifiers


def _ward_link(config: MonitorConfig, data_dir: Path):
    """The ward link with its outbox, over the ward's broker or the hospital engine, as the configuration says."""
    from appliance.alerts.ward_mqtt import mqtt_ward_link
    from appliance.hospital.bedlink import engine_ward_link
    from appliance.store.outbox import Outbox

    c = config.confirmation
    outbox = Outbox(data_dir / OUTBOX_FILE)
    try:
        if config.engine is not None:
            e = config.engine
            return engine_ward_link(e.servers, e.ward, config.bed_id, e.password(), outbox, ca_file=e.ca_file,
                                    confirm=c.confirm, confirm_timeout_s=c.timeout_s)
        m = config.mqtt
        assert m is not None
        return mqtt_ward_link(m.host, m.port, config.bed_id, outbox, client_id=f"appliance-{config.bed_id}",
                              topic_prefix=m.topic_prefix, keepalive_s=m.keepalive_s, username=m.username,
                              password=m.password(), ca_file=m.ca_file, confirm=c.confirm,
                              confirm_timeout_s=c.timeout_s)
    except BaseException:
        outbox.close()
        raise


def _gpio(config: MonitorConfig, source):
    """The buzzer and LED on the board's lines, named by their roles in the board profile."""
    if config.gpio is None:
        return None
    from appliance.alerts.notifiers import GpioNotifier
    from appliance.errors import ConfigError

    pins = source.front_end.profile.gpio
    missing = [role for role in (config.gpio.buzzer, config.gpio.led) if role not in pins]
    if missing:
        raise ConfigError(f"[notify.gpio]: the board profile has no gpio role {missing[0]!r}; it has "
                          f"{', '.join(sorted(pins))}")
    buzzer, led = pins[config.gpio.buzzer], pins[config.gpio.led]
    lines = source.board.gpio(GpioNotifier.request(buzzer, led), consumer="alarm signals")
    return GpioNotifier(lines, buzzer=buzzer, led=led)


def _nurse_call(config: MonitorConfig, source):
    """The nurse-call relays on the board's lines, named by their roles in the board profile; every relay open
    from the moment the lines are requested."""
    if config.nurse_call is None:
        return None
    from appliance.alerts.nurse_call import NurseCallRelays
    from appliance.drivers.bus import LineRequest
    from appliance.errors import ConfigError

    settings, pins = config.nurse_call, source.front_end.profile.gpio
    missing = [role for role in settings.relays.values() if role not in pins]
    if missing:
        raise ConfigError(f"[notify.nurse_call]: the board profile has no gpio role {missing[0]!r} (add it to "
                          f"[board.gpio] with its line); it has {', '.join(sorted(pins))}")
    relays = {priority: pins[role] for priority, role in settings.relays.items()}
    taken = {role: pins[role] for role in ((config.gpio.buzzer, config.gpio.led) if config.gpio else ())}
    clash = [line for line in relays.values() if line in taken.values()]
    if clash:
        raise ConfigError(f"[notify.nurse_call]: line {clash[0]} is the buzzer's or the LED's")
    open_level = 1 if settings.active_low else 0
    lines = source.board.gpio(LineRequest(outputs=dict.fromkeys(relays.values(), open_level), inputs={}),
                              consumer="nurse call")
    return NurseCallRelays(lines, relays, mode=settings.mode, active_low=settings.active_low)
