"""A nurse's whole round with one patient, in headless Chromium at the bedside screen's 800 x 480: admit, the
pressure alarm with the patient named, acknowledged from the live view, a turn recorded from the ward station,
discharge, and the shift report's PDF that tells it all.

Everything runs as on a ward: the monitor (`appliance run`, the virtual bed one simulated minute per wall second,
an alarm dose of 0.05 so the sacral alarm comes about 20 minutes after the admission starts doses afresh), its
screen (`python -m webui`), a real Mosquitto, and the station (`appliance ward`) with its own screen and
accounts. The two screens are opened as 127.0.0.1 and localhost so that their session cookies stay apart, as
two hosts' would. Each step's screenshot is written to ``docs/screenshots/walkthrough-*`` (or
``$SCREENSHOT_DIR``).
"""

import io
import subprocess
import sys
import urllib.request

import pytest
from pypdf import PdfReader
from test_browser import (_answers, bedside, browser, detached, fill, free_port, png_size, screenshot,  # noqa: F401
                          submit_and_wait, text, tiles, viewport, wait_for)
from test_browser_bedside import shown
from webui_client import PASSWORD

BED = "ward3-bed12"                    # the bed test_browser.bedside runs
PATIENT, NAME, BRADEN = "MRN-7731", "Grace Hopper", "12"
SCENE = """
[scene]
description = "supine and still all along"
weight_kg = 75
height_cm = 175
duration_s = 43200

[[event]]
at_s = 0
kind = "lie-down"
posture = "supine"
"""
STEPS = ("admitted", "alarm", "acknowledged", "ward-turn", "turn-recorded", "discharged", "report")

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def ward(tmp_path_factory):
    """The ward's broker and `appliance ward` on it: (the broker's port, the station screen's address)."""
    from mqtt_broker import Broker

    folder = tmp_path_factory.mktemp("ward")
    broker = Broker()
    broker.start()
    (folder / "ward.toml").write_text(f'[broker]\nhost = "127.0.0.1"\nport = {broker.port}\n'
                                      '[station]\nclient_id = "walk-station"\n')
    port = free_port()
    with open(folder / "ward.log", "w") as log:
        station = subprocess.Popen([sys.executable, "-m", "appliance", "ward", "--config", str(folder / "ward.toml"),
                                    "--data-dir", str(folder / "station"), "--listen", f"127.0.0.1:{port}",
                                    "--plain-http"], stdout=log, stderr=subprocess.STDOUT)
    try:
        wait_for(lambda: _answers(f"http://127.0.0.1:{port}/login"), 60, "the station to listen")
        yield broker.port, f"http://localhost:{port}"
    finally:
        station.terminate()
        station.wait(timeout=30)
        broker.stop()


@pytest.fixture(scope="module")
def bedside_screen(tmp_path_factory, bed_monitoring, model_cache, ward):
    """The monitor reporting to the ward and its screen on one data directory: the screen's address."""
    with bedside(tmp_path_factory.mktemp("bedside"), SCENE, model_cache, ward[0], first_frame_s=180) as (base, _):
        yield base


def live(driver) -> dict:
    """The bedside's snapshot as the page's own session reads it."""
    return driver.execute_script("return fetch('/api/live').then(r => r.json());")


def step(driver, n: int, about: str | None = None) -> None:
    """The screenshot of step ``n`` at the bedside screen's size, scrolled to the element ``about`` (an XPath)."""
    if about is not None:
        driver.execute_script("document.evaluate(arguments[0], document, null, XPathResult.FIRST_ORDERED_NODE_TYPE,"
                              " null).singleNodeValue.scrollIntoView({block: 'center'});", about)
    path = screenshot(driver, f"walkthrough-{n + 1}-{STEPS[n]}", 800, 480)
    assert png_size(path) == (800, 480)


def click_until(driver, find, done, what: str, timeout_s: float = 60) -> None:
    """Click what ``find()`` returns until ``done()``: a page redrawn by its stream may replace the button between
    finding and clicking it."""
    from selenium.common.exceptions import ElementNotInteractableException, WebDriverException

    def attempt():
        if done():
            return True
        try:
            button = find()
            if button is not None:
                button.click()
        except ElementNotInteractableException:
            pass
        except WebDriverException as exc:
            if not detached(exc):
                raise
        return done()
    wait_for(attempt, timeout_s, what, poll_s=1.0)


def pdf_text(data: bytes) -> str:
    assert data.startswith(b"%PDF-"), data[:100]
    return " ".join(" ".join(page.extract_text().split()) for page in PdfReader(io.BytesIO(data)).pages)


def test_a_patient_admitted_alarmed_acknowledged_turned_from_the_ward_and_discharged_is_in_the_shift_report(
        bedside_screen, ward, browser):  # noqa: F811
    from selenium.webdriver.common.by import By

    driver, base, station = browser, bedside_screen, ward[1]
    viewport(driver, 800, 480)
    driver.get(base + "/")
    fill(driver, "form", name="admin.ward3", password=PASSWORD, confirm=PASSWORD)
    driver.get(base + "/accounts")
    fill(driver, "#new-account", name="nurse.jones", role="nurse", password=PASSWORD, confirm=PASSWORD)
    submit_and_wait(driver, driver.find_element(By.CSS_SELECTOR, "header form button"))      # log out
    fill(driver, "form", name="nurse.jones", password=PASSWORD)
    assert "nurse.jones (nurse)" in text(driver, "header")

    # 1. Admission at the bedside's patient page.
    driver.get(base + "/patient")
    before = {a["alarm_id"] for a in live(driver).get("alarms", [])}
    fill(driver, "form[action$='/patient/admit']", patient_id=PATIENT, name=NAME, braden=BRADEN)
    assert f"{PATIENT} admitted" in text(driver, ".flash")
    wait_for(lambda: (live(driver).get("patient") or {}).get("patient_id") == PATIENT, 60, "the admission applied")
    driver.get(base + "/patient")
    assert f"{PATIENT} ({NAME})" in text(driver, "main") and f"Braden {BRADEN}" in text(driver, "main")
    assert NAME in text(driver, "#header-patient") and PATIENT in text(driver, "#header-patient")
    step(driver, 0)

    # 2. The sacral alarm of this patient on the live view, the patient named in the header.
    driver.get(base + "/")

    def new_sacral_alarm():
        return next((a for a in live(driver).get("alarms", []) if a["alarm_id"] not in before
                     and a["key"] == "pressure:sacrum"), None)
    alarm = wait_for(new_sacral_alarm, 180, "the sacral alarm after the admission", poll_s=1.0)
    row = f"#alarms .alarm[data-alarm-id='{alarm['alarm_id']}']"
    row_path = f"//div[@id='alarms']/div[@data-alarm-id='{alarm['alarm_id']}']"
    wait_for(lambda: "sacrum" in shown(driver, row), 30, "the alarm on the live view")
    assert PATIENT in shown(driver, "#header-patient") and NAME in shown(driver, "#header-patient")
    assert shown(driver, "#patient") == f"{PATIENT} ({NAME})"
    step(driver, 1, row_path)

    # 3. Acknowledged with the live view's own button, at the bedside screen's size.
    def acknowledge_button():
        found = driver.find_elements(By.CSS_SELECTOR, row + " button.ack")
        return found[0] if found else None
    click_until(driver, acknowledge_button, lambda: "acknowledged" in shown(driver, "#alarm-answer")
                or "acknowledged by" in shown(driver, row),
                "the acknowledgement sent")
    wait_for(lambda: "acknowledged by nurse.jones" in shown(driver, row), 60, "the acknowledgement shown")
    step(driver, 2, row_path)

    # 4. The ward station: a ward nurse records the bed's turn with the tile's own button.
    driver.get(station + "/")
    fill(driver, "form", name="admin.ward3", password=PASSWORD, confirm=PASSWORD)
    driver.get(station + "/accounts")
    fill(driver, "#new-account", name="nurse.patel", role="nurse", password=PASSWORD, confirm=PASSWORD)
    submit_and_wait(driver, driver.find_element(By.CSS_SELECTOR, "header form button"))
    fill(driver, "form", name="nurse.patel", password=PASSWORD)
    assert driver.current_url.endswith("/ward")
    tile = f'article[data-bed="{BED}"]'
    wait_for(lambda: any(t["bed"] == BED for t in tiles(driver)), 60, "the bed's tile at the station")

    def turn_button():
        found = driver.find_elements(By.CSS_SELECTOR, f'{tile} button[aria-label="Record a turn at bed {BED}"]')
        return found[0] if found else None
    click_until(driver, turn_button, lambda: "Record turn by nurse.patel" in shown(driver, tile), "the turn sent")
    wait_for(lambda: "Record turn by nurse.patel: done" in shown(driver, tile), 60, "the bed's answer: done")
    assert f"record a turn at bed {BED}: sent" in shown(driver, "#said")
    step(driver, 3, f"//article[@data-bed='{BED}']/p[contains(@class, 'command')]")

    # 5. Back at the bedside: the turn is the ward nurse's in the bed's turn list.
    driver.get(base + "/history?hours=12")
    turn_rows = "//h2[.='Turns']/following-sibling::table[1]//tbody/tr"
    turns = [r.text for r in driver.find_elements(By.XPATH, turn_rows)]
    assert any("recorded" in r and "ward:nurse.patel" in r for r in turns), turns
    step(driver, 4, f"({turn_rows})[last()]")

    # 6. Discharge at the bedside.
    driver.get(base + "/patient")
    submit_and_wait(driver, driver.find_element(By.CSS_SELECTOR, "form[action$='/patient/discharge'] button"))
    assert f"{PATIENT} discharged" in text(driver, ".flash")
    wait_for(lambda: live(driver).get("patient") is None and live(driver).get("time_s"), 60, "the discharge applied")
    driver.get(base + "/patient")
    assert "No patient admitted" in text(driver, "#header-patient")
    assert any("discharged" in r.text and PATIENT in r.text
               for r in driver.find_elements(By.CSS_SELECTOR, "main table tbody tr"))
    step(driver, 5)

    # 7. The shift report, downloaded through the shift summary's link with the nurse's session.
    driver.get(base + "/history/summary?hours=12")
    link = driver.find_element(By.LINK_TEXT, "Shift report (PDF)").get_attribute("href")
    step(driver, 6)
    cookies = "; ".join(f"{c['name']}={c['value']}" for c in driver.get_cookies())
    with urllib.request.urlopen(urllib.request.Request(link, headers={"Cookie": cookies}), timeout=60) as answer:
        assert answer.headers["Content-Type"] == "application/pdf"
        report = pdf_text(answer.read())
    assert f"Shift report, bed {BED}" in report, report
    assert f"Patient: no patient admitted; discharged in the period: {PATIENT}" in report, report
    assert f"admitted {PATIENT} ({NAME}, Braden {BRADEN}) nurse.jones" in report, report
    assert f"discharged {PATIENT} nurse.jones" in report, report
    clinical = report.split("Clinical alarms", 1)[1].split("Technical alarms", 1)[0]
    rows = clinical.split("sustained pressure at the ")[1:]       # each alarm's row on, up to the next one's
    assert any(r.startswith("sacrum") and "nurse.jones" in r for r in rows), clinical     # acknowledged by the nurse
    assert "turn recorded by ward:nurse.patel" in report, report           # the turn recorded from the ward
