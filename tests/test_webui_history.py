"""The history screen: per-region pressure and dose charts, turns and alarms, the API and the shift summary."""

from pathlib import Path

import numpy as np
import pytest

from appliance.core.pressure_map import HIGH_PRESSURE_MMHG
from appliance.alerts.events import Event
from appliance.alerts.wording import alarm_words
from appliance.core.pressure import KPA_PER_MMHG
from appliance.service.live import LiveChannel
from appliance.store import Store
from webui import create_app
from webui.history import chart, load_history, region_series, summarise
from webui_client import client_as, set_up

DEFAULT_THRESHOLD = HIGH_PRESSURE_MMHG
SACRUM = [(0.0, 40.0, None), (600.0, 45.0, 0.1), (1200.0, 20.0, 0.2), (1800.0, 50.0, 0.4), (3000.0, 38.0, 0.6)]
REGION_2 = [(1200.0, 33.0, 0.05), (1800.0, 31.0, 0.08)]
MAP_TIMES = (0.0, 600.0, 1200.0, 1800.0, 2400.0, 3000.0)      # the sacrum is not loaded at 2400


@pytest.fixture
def app(tmp_path):
    return create_app(tmp_path, secure_cookies=False, TESTING=True)


@pytest.fixture
def nurse(app):
    return client_as(app, "nurse")


@pytest.fixture
def filled(app, tmp_path):
    """A store with six kept maps, two regions, two turns and a reminder, a clinical and a technical alarm."""
    with Store.open(tmp_path / "appliance.db", history_interval_s=0) as store:
        for t in MAP_TIMES:
            regions = [{"id": 1, "zone": "sacrum", "peak_mmhg": p, "area_cm2": 12.0, "dose": d}
                       for time_s, p, d in SACRUM if time_s == t]
            regions += [{"id": 2, "zone": None, "peak_mmhg": p, "area_cm2": 4.0, "dose": d}
                        for time_s, p, d in REGION_2 if time_s == t]
            store.record_map(t, np.full((2, 3), 1.0), regions)
        store.record_events([
            {"time_s": 600.0, "type": "alarm", "kind": "raised", "alarm_id": 2, "key": "technical:front-end",
             "category": "technical", "priority": "medium", "message": "no frame from the front end"},
            Event(900.0, "turn", "repositioned", message="repositioned: on the back to left side, 30 degrees"),
            Event(1200.0, "alarm", "raised", "medium", "clinical", "pressure:sacrum", "sacrum", alarm_id=1,
                  message="sustained pressure at the sacrum: reposition the patient"),
            Event(1500.0, "alarm", "acknowledged", "medium", "clinical", "pressure:sacrum", "sacrum", alarm_id=1,
                  message="sustained pressure at the sacrum", user="nurse.jones"),
            Event(1800.0, "alarm", "ended", "medium", "technical", "technical:front-end", alarm_id=2),
            Event(2000.0, "turn", "repositioned", message="repositioned: left side, 30 degrees to on the back"),
            Event(2700.0, "alarm", "raised", "medium", "clinical", "turn:due", alarm_id=3,
                  message="repositioning is due"),
            Event(3300.0, "alarm", "ended", "medium", "clinical", "pressure:sacrum", "sacrum", alarm_id=1),
        ])
    return app


@pytest.mark.parametrize("path", ["/history", "/history/summary"])
def test_anonymous_pages_are_sent_to_the_login(app, path):
    set_up(app.test_client())
    answer = app.test_client().get(path)
    assert answer.status_code == 302 and "/login" in answer.headers["Location"]


def test_the_anonymous_api_is_refused(app):
    set_up(app.test_client())
    assert app.test_client().get("/api/history").status_code == 401


@pytest.mark.parametrize("hours", ["abc", "", "0", "0.5", "169", "1e3", "nan", "inf", "-inf"])
def test_bad_hours_are_refused_naming_the_parameter_and_range(nurse, hours):
    for path in ("/history", "/api/history", "/history/summary"):
        answer = nurse.get(path, query_string={"hours": hours})
        assert answer.status_code == 400, path
        assert "hours must be a number from 1 to 168" in answer.get_data(as_text=True), path


@pytest.mark.parametrize("hours", ["1", "168", "12.5"])
def test_hours_at_and_inside_the_limits_are_accepted(nurse, hours):
    assert nurse.get("/api/history", query_string={"hours": hours}).status_code == 200


@pytest.mark.parametrize("path", ["/history", "/history/summary"])
def test_before_any_record_the_pages_say_so(nurse, path):
    answer = nurse.get(path)
    assert answer.status_code == 200 and "No history recorded yet" in answer.get_data(as_text=True)


def test_before_any_record_the_api_says_so(nurse):
    data = nurse.get("/api/history").get_json()
    assert data["message"] == "no history recorded yet" and data["regions"] == []


def test_the_api_gives_each_regions_series_the_turns_and_the_alarms(filled, nurse):
    data = nurse.get("/api/history?hours=12").get_json()
    assert (data["from_s"], data["to_s"]) == (0.0, 3300.0)           # from the first record to the newest
    assert data["threshold_mmhg"] == pytest.approx(DEFAULT_THRESHOLD)
    sacrum, other = data["regions"]
    assert (sacrum["region_id"], sacrum["zone"], sacrum["label"]) == (1, "sacrum", "sacrum (region 1)")
    assert sacrum["times"] == [t for t, _, _ in SACRUM]
    assert sacrum["peak_mmhg"] == [p for _, p, _ in SACRUM]
    assert sacrum["dose"] == [d for _, _, d in SACRUM]
    assert (other["label"], other["times"], other["dose"]) == ("region 2", [1200.0, 1800.0], [0.05, 0.08])
    assert [(e["time_s"], e["kind"]) for e in data["turns"]] == [(900.0, "repositioned"), (2000.0, "repositioned")]
    assert [(e["time_s"], e["kind"], e["alarm_id"]) for e in data["alarms"]] == [
        (600.0, "raised", 2), (1200.0, "raised", 1), (1500.0, "acknowledged", 1), (1800.0, "ended", 2),
        (2700.0, "raised", 3), (3300.0, "ended", 1)]


def test_a_short_window_keeps_only_its_end(filled, nurse, tmp_path):
    with Store.open(tmp_path / "appliance.db") as store:
        store.record_events([Event(4500.0, "turn", "bed-empty", message="the bed is empty")])
    data = nurse.get("/api/history?hours=1").get_json()                # 900 s .. 4500 s
    assert (data["from_s"], data["to_s"]) == (900.0, 4500.0)
    assert data["regions"][0]["times"] == [1200.0, 1800.0, 3000.0]
    assert [e["time_s"] for e in data["turns"]] == [900.0, 2000.0, 4500.0]
    assert [e["time_s"] for e in data["alarms"]] == [1200.0, 1500.0, 1800.0, 2700.0, 3300.0]


def test_the_summary_numbers(filled):
    with filled.app_context():
        summary = summarise(load_history(12.0), DEFAULT_THRESHOLD)
    assert (summary.start_s, summary.end_s) == (0.0, 3300.0)
    assert (summary.turns, summary.turn_reminders) == (2, 1)
    assert summary.longest_without_turn_s == 1300.0                     # the last turn at 2000 s to the end
    sacrum, other = summary.regions
    # at or above 32 mmHg from 0, 600, 1800 (to the next kept map, 600 s each) and 3000 (to the end, 300 s)
    assert (sacrum.peak_mmhg, sacrum.max_dose, sacrum.minutes_above) == (50.0, 0.6, 35.0)
    assert (other.peak_mmhg, other.max_dose, other.minutes_above) == (33.0, 0.08, 10.0)
    (clinical, reminder), (technical,) = summary.clinical, summary.technical
    assert (reminder.key, reminder.ended_s) == ("turn:due", None)
    assert (clinical.alarm_id, clinical.priority, clinical.acknowledged_by) == (1, "medium", "nurse.jones")
    assert clinical.acknowledge_delay_s == 300.0 and clinical.ended_s == 3300.0
    assert (technical.key, technical.acknowledged_by, technical.acknowledge_delay_s) == ("technical:front-end",
                                                                                           None, None)


def test_the_summary_page_shows_them_with_the_bed_and_a_print_button(filled, nurse, tmp_path):
    live = LiveChannel(tmp_path / "live.json")
    live.publish({"bed_id": "bed-7", "time_s": 3300.0, "sequence": 1, "frame_interval_s": 1.0})
    live.close()
    page = nurse.get("/history/summary").get_data(as_text=True)
    assert "bed bed-7" in page and 'id="print"' in page and "static/print.js" in page and "@media print" not in page
    with nurse.get("/static/print.js") as script:
        assert "window.print()" in script.get_data(as_text=True)
    assert "Period 0:00:00 to 0:55:00 (55 min)" in page
    assert "2 turns; longest time without a turn\n  <strong>22 min</strong>" in page
    assert "<td>sacrum (region 1)</td><td>50</td>\n        <td>0.60</td><td>35</td>" in page
    clinical, technical = page.split("Technical alarms")
    assert "nurse.jones" in clinical and "<td>5 min</td>" in clinical and "technical:" not in clinical
    assert "no frame from the front end" in technical and "not acknowledged" in technical


def test_the_summary_prints_without_the_header_and_buttons(app, nurse):
    assert "static/history.css" in nurse.get("/history/summary").get_data(as_text=True)
    css = (Path(app.static_folder) / "history.css").read_text()
    print_rules = css.split("@media print", 1)[1]
    assert "header" in print_rules and ".no-print" in print_rules and "display: none" in print_rules


def test_a_threshold_in_the_live_settings_is_used(filled, nurse, tmp_path):
    live = LiveChannel(tmp_path / "live.json")
    live.publish({"bed_id": "bed-7", "time_s": 3300.0, "sequence": 1, "frame_interval_s": 1.0,
                  "settings": {"threshold_kpa": 42.0 * KPA_PER_MMHG}})
    live.close()
    assert nurse.get("/api/history").get_json()["threshold_mmhg"] == pytest.approx(42.0)
    assert "Minutes at or above 42 mmHg" in nurse.get("/history/summary").get_data(as_text=True)


def test_the_page_draws_one_chart_per_region_with_turns_and_alarms(filled, nurse):
    page = nurse.get("/history").get_data(as_text=True)
    assert page.count('<svg class="chart"') == 2
    assert "<figcaption>sacrum (region 1)</figcaption>" in page and "<figcaption>region 2</figcaption>" in page
    sacrum_chart, other_chart = page.split('<svg class="chart"')[1:]
    assert sacrum_chart.count('class="marker turn"') == 2 == other_chart.count('class="marker turn"')
    assert sacrum_chart.count('class="marker acknowledged"') == 1            # the sacrum's own alarm
    assert other_chart.count('class="marker acknowledged"') == 0
    assert sacrum_chart.count('class="marker raised"') == 3          # its alarm, the technical one, the turn reminder
    assert 'class="threshold"' in sacrum_chart and 'class="dose-one"' in sacrum_chart
    assert "sustained pressure at the sacrum" in page and "repositioning is due" in page


def test_a_region_line_breaks_where_a_kept_map_lacked_it(filled):
    with filled.app_context():                  # the chart's turn marks read the site's clock
        history = load_history(12.0)
        sacrum = region_series(history.regions)[0]
        drawn = chart(sacrum, history, DEFAULT_THRESHOLD)
    assert [len(run.split()) for run in drawn.pressure] == [4, 1]            # 0-1800 s, then 3000 s alone
    assert [len(run.split()) for run in drawn.dose] == [3, 1]                # no dose yet at 0 s
    assert drawn.left < float(drawn.pressure[0].split()[0].split(",")[0]) + 1 and drawn.threshold_y < drawn.bottom


def test_the_running_monitors_regions_and_alarm_are_on_the_page(small_mat_calibration, tmp_path):
    """The monitor daemon and the screen share a data directory; every frame's map is kept (600 s a frame)."""
    from test_daemon import FlakySource, small_daemon

    daemon, events = small_daemon(small_mat_calibration, tmp_path, FlakySource(failing=()), alarm_dose=0.05)
    daemon.run(10)
    daemon.close()
    raised = next(e for e in events if e.kind == "raised" and e.key.startswith("pressure:"))
    app = create_app(tmp_path, secure_cookies=False, TESTING=True)
    nurse = client_as(app, "nurse")
    data = nurse.get("/api/history").get_json()
    assert data["regions"] and len(data["regions"][0]["times"]) == 10
    assert data["regions"][0]["dose"][-1] > 0.05
    page = nurse.get("/history").get_data(as_text=True)
    assert page.count('<svg class="chart"') == len(data["regions"])
    assert f"<figcaption>{data['regions'][0]['label']}</figcaption>" in page
    assert alarm_words(raised.key) in page and raised.key not in page and "raised" in page
    summary = nurse.get("/history/summary").get_data(as_text=True)
    assert raised.message in summary and "not acknowledged" in summary


@pytest.mark.parametrize("path", ["/history", "/alarms", "/history/summary"])
def test_nurse_pages_name_alarms_in_words_not_by_their_keys(filled, nurse, path):
    page = nurse.get(path).get_data(as_text=True)
    for key in ("pressure:sacrum", "technical:front-end", "turn:due"):
        assert key not in page, (path, key)
    if path != "/history/summary":                     # the summary lists clinical alarms by their messages
        assert "Pressure at the sacrum" in page and "Equipment: measuring electronics" in page
