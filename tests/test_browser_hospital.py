"""The hospital overview as the night coordinator opens it: `appliance hospital overview` as its own process on a
real PostgreSQL history, in Chromium at the desktop's 1920 x 1080: the first account, then every ward with its
beds heard and open alarms, the ward needing help first."""

import datetime as dt
import subprocess
import sys

import psycopg
from postgres_server import running_postgres
from test_browser import _answers, browser, fill, free_port, png_size, screenshot, text, wait_for  # noqa: F401
from test_hospital_overview import HOSPITAL, alarm
from webui_client import PASSWORD

from appliance.hospital.description import description_text
from appliance.hospital.history.schema import create_schema
from appliance.hospital.history.store import write_events, write_minutes
from appliance.hospital.history.trend import Minute


def test_the_coordinator_sees_which_ward_needs_help(browser, tmp_path):  # noqa: F811
    from selenium.webdriver.common.by import By

    now = dt.datetime.now(dt.UTC)
    with running_postgres() as postgres:
        postgres.psql("CREATE DATABASE overview")
        with psycopg.connect(postgres.dsn("overview")) as db:
            create_schema(db)
            write_events(db, [alarm("ward4", "w4-bed02", 1, 40, 5, "raised", "high", "occiput", now),
                              alarm("ward3", "w3-bed01", 1, 20, 2, "raised", "medium", "heel-right", now)])
            write_minutes(db, [Minute(ward, bed, now.replace(second=0, microsecond=0), 30, 30, 35.0, 35.0, "supine",
                                      last_at=now) for ward, bed in (("ward3", "w3-bed01"), ("ward4", "w4-bed02"))])
        description = tmp_path / "hospital.toml"
        description.write_text(description_text(HOSPITAL))
        port = free_port()
        server = subprocess.Popen([sys.executable, "-m", "appliance", "hospital", "overview", "--description",
                                   str(description), "--dsn", postgres.dsn("overview"), "--data-dir",
                                   str(tmp_path / "overview"), "--listen", str(port), "--plain-http"],
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        try:
            base = f"http://127.0.0.1:{port}"
            wait_for(lambda: _answers(base + "/login"), 60, "the overview's screen")
            browser.get(base + "/")
            fill(browser, "form", name="admin.hospital", password=PASSWORD, confirm=PASSWORD)
            browser.get(base + "/hospital")
            rows = browser.find_elements(By.CSS_SELECTOR, "#wards tbody tr")
            assert [r.find_element(By.TAG_NAME, "td").text for r in rows] == ["ward4", "ward3"]   # high first
            assert "alarm-high" in rows[0].get_attribute("class")
            assert "1 of 2" in rows[0].text and "1 of 3" in rows[1].text
            assert [c.text for c in rows[0].find_elements(By.TAG_NAME, "td")][6:8] == ["1", "1"]   # hour, day
            assert "w3-bed02, w3-bed03" in rows[1].text                                  # silent beds named
            alarms = text(browser, "#open-alarms")
            assert alarms.index("occiput") < alarms.index("heel-right")
            path = screenshot(browser, "hospital", 1920, 1080)
            assert png_size(path) == (1920, 1080)
            width = browser.execute_script("return document.documentElement.scrollWidth")
            assert width <= 1920                                                         # no sideways scrolling
        finally:
            server.terminate()
            output = server.communicate(timeout=30)[0]
    assert "hospital overview: 2 ward(s)" in output
