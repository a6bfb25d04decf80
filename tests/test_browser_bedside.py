"""The bedside screen in headless Chromium at 800 x 480: touch-sized controls, no sideways scrolling, alarm signals
as IEC 60601-1-8 sets them (flash rates, tone timing) and acknowledging an alarm from the live view.

The monitor is not run: a ``live.json`` written with the monitor's own :class:`LiveChannel` stands in for it,
and each test rewrites it to show what it needs. The screen is ``python -m webui``, as on the appliance; the
commands it queues are read from the monitor's store. Screenshots go to ``docs/screenshots``.
"""

import itertools
import re
import subprocess
import sys

import pytest
from test_browser import _answers, browser, free_port, png_size, screenshot, text, viewport, wait_for  # noqa: F401
from webui_client import PASSWORD

from appliance.alerts.tones import tone_schedule
from appliance.service.live import LiveChannel
from appliance.store import Store
from appliance.accounts.users import UserStore

pytestmark = pytest.mark.slow
NURSE_PAGES = ("/", "/alarms", "/patient", "/history", "/history/summary", "/settings", "/account/password")
ROWS, COLUMNS, PITCH_MM = 8, 16, (125.0, 112.5)          # a bed mat lying along x, as grid-8x16
HIGH = {"alarm_id": 1, "key": "pressure:sacrum", "priority": "high", "category": "clinical",
        "message": "Pressure at the sacrum", "raised_s": 3000.0}
MEDIUM = {"alarm_id": 2, "key": "technical:ward-link", "priority": "medium", "category": "technical",
          "message": "Equipment: link to the ward station", "raised_s": 3300.0}
LOW = {"alarm_id": 3, "key": "turn:due", "priority": "low", "category": "clinical", "message": "Turn due",
       "raised_s": 3500.0}


def snapshot(alarms=(HIGH, MEDIUM, LOW), due_in_s=2400.0, frame_interval_s=3600.0, acknowledged=()) -> dict:
    """A live view with a hot spot at the sacrum; fresh for an hour unless ``frame_interval_s`` says otherwise."""
    mmhg = [[5.0 + (60.0 if 5 <= column <= 7 and 3 <= row <= 4 else 0.0) for column in range(COLUMNS)]
            for row in range(ROWS)]
    alarms = [{"state": "active", "delivery": None, "audio_paused": False,
               "acknowledged_by": "nurse.bedside" if a["alarm_id"] in acknowledged else None, **a} for a in alarms]
    loud = [a["priority"] for a in alarms if not a["acknowledged_by"]]
    return {"time_s": 3600.0, "frame_interval_s": frame_interval_s, "sequence": 60, "bed_id": "ward3-bed12",
            "map": {"mmhg": mmhg, "pixel_mm": list(PITCH_MM), "peak_kpa": 65.0 * 0.133322, "usable_readings": 128},
            "regions": [{"id": 1, "zone": "sacrum", "words": "sacrum", "peak_mmhg": 65.0, "area_cm2": 400.0,
                         "x_mm": 750.0, "y_mm": 450.0, "since_s": 2400.0, "dose": 0.8}],
            "alarms": alarms, "audible": max(loud, key=("low", "medium", "high").index) if loud else None,
            "patient": {"patient_id": "MRN-0042", "name": "Ada Byron", "braden": 14, "bed_exit_alert": False},
            "posture": "supine", "posture_words": "on the back", "posture_sure": True,
            "turn": {"due_in_s": due_in_s, "turning_since_s": None},
            "status": {"maps": 60, "faults": 0, "source": "hardware"}, "ward_link": None, "settings_changed": []}


def publish(data_dir, live: dict) -> None:
    channel = LiveChannel(data_dir / "live.json")
    channel.publish(live)
    channel.close()


@pytest.fixture(scope="module")
def screen(tmp_path_factory):
    """The screen on a data directory with a live view, a nurse account and the monitor's store; its address."""
    data_dir = tmp_path_factory.mktemp("bedside")
    (data_dir / "settings.toml").write_text('[monitor]\ntime_zone = "America/New_York"\n')    # the site's clock
    publish(data_dir, snapshot())
    Store.open(data_dir / "appliance.db").close()
    users = UserStore(data_dir / "webui.db")
    users.create("admin.ward3", PASSWORD, "admin", by="admin.ward3")
    users.create("nurse.bedside", PASSWORD, "nurse", by="admin.ward3")
    port = free_port()
    with open(data_dir / "screen.log", "w") as log:
        process = subprocess.Popen([sys.executable, "-m", "webui", "--data-dir", str(data_dir), "--port", str(port),
                                    "--plain-http"], stdout=log, stderr=subprocess.STDOUT)
    try:
        base = f"http://127.0.0.1:{port}"
        wait_for(lambda: _answers(base + "/login"), 30, "the screen to listen")
        yield base, data_dir
    finally:
        process.terminate()
        process.wait(timeout=30)


@pytest.fixture
def nurse(screen, browser):  # noqa: F811
    """The browser logged in as a nurse on the live view, with the live view reset to three open alarms."""
    from selenium.webdriver.common.by import By

    base, data_dir = screen
    publish(data_dir, snapshot())
    viewport(browser, 800, 480)
    browser.get(base + "/")
    if "/login" in browser.current_url:
        browser.find_element(By.NAME, "name").send_keys("nurse.bedside")
        browser.find_element(By.NAME, "password").send_keys(PASSWORD)
        browser.find_element(By.CSS_SELECTOR, "form button[type=submit]").click()
        wait_for(lambda: browser.current_url.rstrip("/") == base, 10, "the live view after logging in")
    wait_for(lambda: "frame 60" in text(browser, "#status"), 15, "the live view drawn")
    return browser


def shown(driver, css: str) -> str:
    """The text of the elements ``css`` selects, read in one script: the live view redraws between two reads."""
    return driver.execute_script("return Array.from(document.querySelectorAll(arguments[0]), e => e.innerText)"
                                 ".join(' ');", css)


def tap(driver, css: str) -> None:
    """A touch screen's tap (touch start and end, no mouse) at the middle of the element ``css`` selects."""
    x, y = driver.execute_script("const r = document.querySelector(arguments[0]).getBoundingClientRect();"
                                 "return [r.x + r.width / 2, r.y + r.height / 2];", css)
    driver.execute_cdp_cmd("Emulation.setTouchEmulationEnabled", {"enabled": True, "maxTouchPoints": 1})
    try:
        for kind, points in (("touchStart", [{"x": x, "y": y}]), ("touchEnd", [])):
            driver.execute_cdp_cmd("Input.dispatchTouchEvent", {"type": kind, "touchPoints": points})
    finally:
        driver.execute_cdp_cmd("Emulation.setTouchEmulationEnabled", {"enabled": False})


CONTROLS = """return Array.from(document.querySelectorAll('a, button, input, select, textarea, header nav strong'))
  .filter(e => e.offsetParent !== null && e.type !== 'hidden')
  .map(e => { const r = e.getBoundingClientRect();
              return {what: e.outerHTML.slice(0, 80), width: r.width, height: r.height}; });"""


@pytest.mark.parametrize("width, height", [(800, 480), (1920, 1080)], ids=["bedside", "desktop"])
def test_every_nurse_page_fits_the_screen_with_controls_a_finger_can_hit(screen, nurse, width, height):
    base, _ = screen
    viewport(nurse, width, height)
    try:
        for path in NURSE_PAGES:
            nurse.get(base + path)
            sizes = nurse.execute_script("const d = document.documentElement; return [d.scrollWidth, d.clientWidth];")
            assert sizes[0] <= sizes[1], f"{path} scrolls sideways at {width} x {height}: {sizes}"
            controls = nurse.execute_script(CONTROLS)
            assert controls, f"no controls found on {path}"
            small = [c for c in controls if c["width"] < 44 or c["height"] < 44]
            assert small == [], f"controls under 44 x 44 px on {path} at {width} x {height}: {small}"
            assert "Ada Byron" in shown(nurse, "header #header-patient")
    finally:
        viewport(nurse, 800, 480)                   # the other tests see the bedside screen


FLASH = """return Array.from(document.querySelectorAll(arguments[0])).map(e => {
  const s = getComputedStyle(e);
  return {name: s.animationName, seconds: parseFloat(s.animationDuration), steps: s.animationTimingFunction,
          border: s.borderTopStyle, text: e.innerText}; });"""


KEYFRAMES = """for (const sheet of document.styleSheets) for (const rule of sheet.cssRules)
  if (rule instanceof CSSKeyframesRule && rule.name === arguments[0]) return Array.from(rule.cssRules, k => k.keyText);
return null;"""


def test_alarms_flash_at_the_standards_rates_and_equipment_alarms_look_different(screen, nurse):
    _, data_dir = screen
    high, medium, low = (nurse.execute_script(FLASH, f".alarm.{p}")[0] for p in ("high", "medium", "low"))
    assert 1.4 <= 1 / high["seconds"] <= 2.8 and high["name"] != "none"
    assert 0.4 <= 1 / medium["seconds"] <= 0.8 and medium["name"] != "none"
    assert low["name"] == "none"                                                  # low priority: steady
    assert high["steps"] == medium["steps"] == "steps(1)"                         # on/off, not a fade
    for flash in (high, medium):                                                  # on half the period: 50 % duty
        assert nurse.execute_script(KEYFRAMES, flash["name"]) == ["0%", "50%"]
    assert "EQUIPMENT" in medium["text"] and medium["border"] == "dashed"
    assert "PATIENT" in high["text"] and high["border"] != "dashed"
    assert high["text"].startswith("PATIENT") and "!!! HIGH: Pressure at the sacrum" in high["text"]
    screenshot(nurse, "live-alarms", 800, 480)
    assert png_size(screenshot(nurse, "live-alarms", 1920, 1080)) == (1920, 1080)

    publish(data_dir, snapshot(alarms=(), frame_interval_s=0.5))                  # then the monitor stops
    stale = wait_for(lambda: nurse.execute_script(FLASH, "#stale:not([hidden])"), 15, "the stale banner")[0]
    assert 0.4 <= 1 / stale["seconds"] <= 0.8 and stale["border"] == "dashed"     # technical, medium
    assert "EQUIPMENT" in stale["text"]
    assert nurse.execute_script("return soundFor({stale: true, alarms: []});") == "medium"


def test_the_tone_for_each_priority_is_timed_as_the_standard_says(nurse):
    schedules = {p: nurse.execute_script("return toneSchedule(arguments[0]);", p) for p in ("high", "medium", "low")}
    for priority, s in schedules.items():
        assert all(75 <= p["lengthMs"] <= 200 for p in s["pulses"]), priority
        assert 150 <= s["hz"] <= 1000, priority
        harmonics = [h for h in s["harmonicsHz"][1:] if 300 <= h <= 4000]
        assert len(harmonics) >= 4, priority
        assert s["burstMs"] == s["pulses"][-1]["startMs"] + s["pulses"][-1]["lengthMs"]
    starts = [p["startMs"] for p in schedules["high"]["pulses"]]
    gaps = [b - a for a, b in itertools.pairwise(starts)]
    breaks = [i + 1 for i, gap in enumerate(gaps) if gap > min(gaps)]
    assert len(starts) == 10 and breaks == [3, 5, 8]                      # 3 + 2 + 3 + 2
    assert 2500 <= schedules["high"]["restMs"] <= 15000
    assert len(schedules["medium"]["pulses"]) == 3 and 2500 <= schedules["medium"]["restMs"] <= 30000
    assert 1 <= len(schedules["low"]["pulses"]) <= 2 and schedules["low"]["restMs"] > 15000
    for priority, s in schedules.items():                      # the same schedule as the bedside buzzer's
        buzzer = tone_schedule(priority)
        assert [(p["startMs"], p["lengthMs"]) for p in s["pulses"]] == \
            [(round(start * 1000), round(length * 1000)) for start, length in buzzer.pulses]
        assert (s["restMs"], s["periodMs"]) == (round(buzzer.rest_s * 1000), round(buzzer.period_s * 1000))
    with pytest.raises(Exception, match="no alarm tone for priority"):
        nurse.execute_script("return toneSchedule('loud');")


def test_only_an_alarm_neither_acknowledged_nor_paused_sounds_and_only_after_sound_on(nurse):
    from selenium.webdriver.common.by import By

    loudest = "return soundFor({alarms: arguments[0], audible: 'x'});"
    alarms = [{"alarm_id": 1, "priority": "high", "acknowledged_by": "nurse.bedside"},
              {"alarm_id": 2, "priority": "medium", "audio_paused": True},
              {"alarm_id": 3, "priority": "low"}]
    assert nurse.execute_script(loudest, alarms) == "low"
    assert nurse.execute_script(loudest, alarms[:2]) is None
    assert nurse.execute_script("return soundFor({alarms: arguments[0], audible: null});", alarms) is None
    assert nurse.execute_script("return sound.priority;") == "high"
    assert nurse.execute_script("return sound.enabled;") is False                 # no touch yet: silent
    button = nurse.find_element(By.ID, "sound-on")
    assert button.is_displayed() and "until you press Sound on" in shown(nurse, "#sound-state")
    nurse.execute_script("window.failures = []; window.addEventListener('error', e => failures.push(e.message));"
                         "window.addEventListener('unhandledrejection', e => failures.push(String(e.reason)));")
    tap(nurse, "#sound-on")                                                       # a touch is gesture enough
    wait_for(lambda: nurse.execute_script("return sound.enabled;"), 5, "the sound to be switched on")
    nurse.execute_script("sound.play(toneSchedule('low'));")                      # the pulses build and start
    assert nurse.execute_script("return failures;") == []
    assert not button.is_displayed() and shown(nurse, "#sound-state") == "Alarm sound on."


def test_the_map_is_marked_as_a_body_and_the_turn_clock_changes_colour(screen, nurse):
    _, data_dir = screen
    sides = {side: shown(nurse, f"#side-{side}") for side in ("top", "bottom", "left", "right")}
    assert sides == {"top": "patient's RIGHT", "bottom": "patient's LEFT", "left": "HEAD", "right": "FEET"}
    tall = nurse.execute_script("return mapSides({mmhg: [[0], [0], [0]], pixel_mm: [100, 100]});")
    assert tall == {"top": "HEAD", "bottom": "FEET", "left": "patient's RIGHT", "right": "patient's LEFT"}
    colours = {}
    for due_in_s, state in ((2400.0, "ok"), (600.0, "soon"), (-300.0, "overdue")):
        publish(data_dir, snapshot(due_in_s=due_in_s))
        wait_for(lambda: state in nurse.find_element("id", "turn").get_attribute("class").split(), 10,  # noqa: B023
                 f"the turn clock {state}")
        colours[state] = nurse.execute_script("return getComputedStyle(document.getElementById('turn'))"
                                              ".backgroundColor;")
    assert colours == {"ok": "rgb(46, 125, 50)", "soon": "rgb(255, 179, 0)", "overdue": "rgb(198, 40, 40)"}
    assert nurse.execute_script("return [turnState(1801), turnState(1800), turnState(0), turnState(-1)];") == \
        ["ok", "soon", "soon", "overdue"]
    expected = nurse.execute_script("return fetch('/api/live').then(r => r.json()).then(s => "
                                    "new Date((s.written_at - 300) * 1000).toLocaleTimeString([], "
                                    "{hour: '2-digit', minute: '2-digit', timeZone: 'America/New_York', "
                                    "timeZoneName: 'short'}));")
    assert shown(nurse, "#turn-at") == f"(at {expected})"           # the wall-clock time it was due, 5 min ago
    # New York's clocks go back at 06:00 UTC on 1 November 2026: 05:30 and 06:30 UTC both read 1:30, told apart.
    edt, est = (nurse.execute_script(f"return clockTime({{written_at: {t}, time_s: 0}}, 0);")
                for t in (1793511000, 1793514600))
    assert re.search(r"\b0?1:30\b.*\bEDT\b", edt) and re.search(r"\b0?1:30\b.*\bEST\b", est)


def test_the_header_names_the_patient_of_the_newest_frame_without_a_reload(screen, nurse):
    _, data_dir = screen
    assert shown(nurse, "#header-patient") == "Patient Ada Byron MRN-0042"
    publish(data_dir, {**snapshot(), "sequence": 61, "patient": None})                 # discharged
    wait_for(lambda: shown(nurse, "#header-patient") == "No patient admitted", 10, "the discharge in the header")
    publish(data_dir, {**snapshot(), "sequence": 62, "patient": {"patient_id": "MRN-7731", "name": None}})
    wait_for(lambda: shown(nurse, "#header-patient") == "Patient MRN-7731", 10, "the admission in the header")
    assert nurse.find_element("id", "header-patient").get_attribute("class") == "patient"


def test_a_nurse_acknowledges_an_alarm_from_the_live_view(screen, nurse):
    from selenium.webdriver.common.by import By

    _, data_dir = screen
    with Store.open(data_dir / "appliance.db") as store:
        before = len(store.pending_commands())
    row = nurse.find_element(By.CSS_SELECTOR, '.alarm[data-alarm-id="1"]')
    row.find_element(By.CSS_SELECTOR, "button.ack").click()
    wait_for(lambda: "acknowledgement sent" in shown(nurse, '.alarm[data-alarm-id="1"]'), 10, "the sent note")
    assert shown(nurse, "#alarm-answer") == "alarm 1 acknowledged; the monitor applies it at its next frame"
    with Store.open(data_dir / "appliance.db") as store:
        commands = store.pending_commands()[before:]
    assert [(c["kind"], c["args"], c["user"]) for c in commands] == [("acknowledge", {"alarm_id": 1},
                                                                       "nurse.bedside")]
    assert nurse.execute_script("return sound.priority;") == "medium"           # the high one is quiet here
    publish(data_dir, snapshot(acknowledged=(1,)))                               # the monitor applied it
    wait_for(lambda: "acknowledged by nurse.bedside" in shown(nurse, '.alarm[data-alarm-id="1"]'), 10,
             "the alarm shown acknowledged")
    assert nurse.find_elements(By.CSS_SELECTOR, '.alarm[data-alarm-id="1"] button') == []
    tap(nurse, '.alarm[data-alarm-id="2"] button.pause')                       # a finger, not a mouse
    wait_for(lambda: "sound pause sent" in shown(nurse, '.alarm[data-alarm-id="2"]'), 10, "the pause sent")
    with Store.open(data_dir / "appliance.db") as store:
        assert store.pending_commands()[-1]["args"] == {"duration_s": 120.0, "alarm_id": 2}
