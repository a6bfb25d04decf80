"""Every page and ward tile says SIMULATED when the data come from the virtual bed or an emulated front end."""

import html
import re

import pytest
from webui_client import client_as

from appliance.service.config_sections import MqttSettings
from appliance.service.daemon import ward_summary
from appliance.service.live import LiveChannel
from appliance.ward.config import WardConfig
from webui import create_app
from webui.live import SIMULATED
from webui.ward import _bed

PAGES = ("/", "/alarms", "/patient", "/history", "/settings", "/engineering", "/accounts")
BANNER = re.compile(r'<p id="simulated"[^>]*>([^<]*)</p>')


def monitor_writes(folder, source):
    live = LiveChannel(folder / "live.json")
    live.publish({"bed_id": "bed-4", "time_s": 60.0, "sequence": 1, "frame_interval_s": 1.0, "regions": [],
                  "alarms": [], "turn": {"due_in_s": 7000.0}, "status": {"maps": 1, "faults": 0, "source": source}})
    live.close()


def banner(page: str) -> tuple[bool, str]:
    """(shown, text) of the page's SIMULATED banner."""
    tag = re.search(r'<p id="simulated"[^>]*>', page)
    assert tag is not None, "every page has the banner's place"
    return "hidden" not in tag.group(0), html.unescape(BANNER.search(page).group(1).strip())


@pytest.mark.parametrize(("source", "expected"), [("virtual", "SIMULATED: the virtual bed, not a patient"),
                                                  ("emulated", "SIMULATED: an emulated front end, not a patient's mat"),
                                                  ("hardware", "")])
def test_every_page_says_simulated_unless_a_real_front_end_reads_a_patient(tmp_path, source, expected):
    app = create_app(tmp_path, secure_cookies=False, TESTING=True)
    monitor_writes(tmp_path, source)
    admin = client_as(app, "admin")
    for page in PAGES:
        answer = admin.get(page)
        assert answer.status_code == 200, page
        assert banner(answer.get_data(as_text=True)) == (bool(expected), expected), page
    assert banner(admin.get("/login").get_data(as_text=True)) == (bool(expected), expected)   # before login too


def test_before_the_monitor_wrote_anything_no_banner_is_claimed(tmp_path):
    app = create_app(tmp_path, secure_cookies=False, TESTING=True)
    assert banner(client_as(app, "nurse").get("/").get_data(as_text=True)) == (False, "")


def test_the_ward_tile_of_a_simulated_bed_says_so_and_a_real_one_does_not():
    snapshot = {"bed_id": "bed-4", "time_s": 60.0, "regions": [], "alarms": [], "turn": {"due_in_s": 10.0},
                "status": {"maps": 3, "faults": 0, "source": "virtual"}}
    summary = ward_summary(snapshot)
    assert summary["status"]["source"] == "virtual"                  # the bed tells the station its source
    station_bed = {"bed_id": "bed-4", "online": True, "status": "online", "last_heard_at": None,
                   "highest_priority": None, "alarms": [], "summary": summary}
    config = WardConfig(MqttSettings("127.0.0.1"))
    assert _bed(station_bed, 0.0, config)["simulated"] == SIMULATED["virtual"]
    summary["status"]["source"] = "hardware"
    assert _bed(station_bed, 0.0, config)["simulated"] is None
