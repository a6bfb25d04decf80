"""The web screen with Flask's test client: first start, login, roles, CSRF, rate limiting, the live view."""

import json
import re
import sqlite3
import subprocess
import sys
import time

import pytest
from flask import url_for
from mqtt_broker import free_port
from webui_client import nurse_beside_a_monitor, PASSWORD, client_as, log_in, set_up, token

from appliance.accounts.users import AccountError, UserStore
from appliance.service.config_sections import MqttSettings
from appliance.service.live import LiveChannel, read_live
from appliance.store import Store
from appliance.ward.config import WardConfig
from appliance.ward.station import WardStation
import webui.live
from webui import create_app, create_ward_app
from webui.limiter import ADDRESS_ATTEMPTS, LoginLimiter


@pytest.fixture
def app(tmp_path):
    return create_app(tmp_path, secure_cookies=False, TESTING=True, STREAM_MAX_S=1.0)


@pytest.fixture(params=["bed", "ward"])
def every_app(request, tmp_path):
    """The bed's screen and the ward station's (its station on a port where no broker answers)."""
    if request.param == "bed":
        yield create_app(tmp_path, secure_cookies=False, TESTING=True, STREAM_MAX_S=1.0)
        return
    with WardStation("127.0.0.1", free_port(), client_id="route-walker") as station:
        yield create_ward_app(tmp_path, station, WardConfig(MqttSettings("127.0.0.1")), secure_cookies=False,
                              TESTING=True, STREAM_MAX_S=1.0)


def test_a_fresh_screen_sends_everyone_to_set_up_the_first_admin(app):
    client = app.test_client()
    assert client.get("/").headers["Location"].endswith("/setup")
    assert client.get("/login").headers["Location"].endswith("/setup")
    assert set_up(client).headers["Location"].endswith("/")
    assert client.get("/").status_code == 200                               # logged in as the admin
    assert app.extensions["users"].get("admin.ward3").role == "admin"
    assert client.get("/setup").headers["Location"].endswith("/login")      # gone once there is an account


@pytest.mark.parametrize("name, password, confirm, message", [
    ("admin", "short", "short", "at least 10 characters"),
    ("Admin Ward", PASSWORD, PASSWORD, "a user name is 2-32 lower-case letters"),
    ("admin", PASSWORD, PASSWORD + "x", "the two passwords differ"),
    ("admin.password", "admin.password", "admin.password", "must not contain the user name"),
])
def test_a_weak_first_account_is_refused_with_the_reason_and_nothing_is_made(app, name, password, confirm, message):
    client = app.test_client()
    answer = client.post("/setup", data={"name": name, "password": password, "confirm": confirm,
                                         "csrf_token": token(client, "/setup")})
    assert answer.status_code == 400 and message in answer.get_data(as_text=True)
    assert app.extensions["users"].count() == 0


def test_login_logout_and_the_audit_log(app):
    set_up(app.test_client())
    app.extensions["users"].create("nurse.jones", PASSWORD, "nurse", by="admin.ward3")
    client = app.test_client()
    assert log_in(client, "nurse.jones", "wrong password!").status_code == 401
    assert log_in(client, "nurse.jones").headers["Location"].endswith("/")
    assert client.get("/api/live").status_code == 200
    assert client.post("/logout", data={"csrf_token": token(client, "/")}).status_code == 302
    assert client.get("/api/live").status_code == 401
    actions = [(e["user"], e["action"]) for e in app.extensions["users"].audit_log()]
    assert actions[:4] == [("nurse.jones", "logged out"), ("nurse.jones", "logged in"),
                           ("nurse.jones", "login failed"), ("admin.ward3", "account created")]


def test_the_next_page_after_login_stays_on_this_site(app):
    set_up(app.test_client())
    client = app.test_client()
    answer = client.post("/login?next=//evil.example/x", data={"name": "admin.ward3", "password": PASSWORD,
                                                                "csrf_token": token(client)})
    assert answer.headers["Location"] == "/"


PUBLIC = {"auth.login", "auth.setup", "static"}


def every_route(app, method):
    """(url, endpoint) for every route of every blueprint answering ``method``, with made-up path arguments."""
    with app.test_request_context():
        for rule in app.url_map.iter_rules():
            if method in rule.methods:
                args = {name: 1 if converter == "int" else "x"
                        for converter, name in re.findall(r"<(?:(\w+):)?(\w+)>", rule.rule)}
                yield url_for(rule.endpoint, **args), rule.endpoint


def test_every_non_public_route_refuses_an_anonymous_request(every_app):
    app = every_app
    set_up(app.test_client())
    checked = 0
    for method in ("GET", "POST"):
        for url, endpoint in every_route(app, method):
            if endpoint in PUBLIC:
                continue
            client = app.test_client()
            data = {"csrf_token": token(client)} if method == "POST" else None
            answer = client.open(url, method=method, data=data)
            assert answer.status_code in (302, 401), (method, url)
            assert answer.status_code == 401 or "/login" in answer.headers["Location"], (method, url)
            checked += 1
    assert checked >= 5


def test_every_state_changing_request_needs_the_csrf_token(every_app):
    """Logged in as the admin (allowed everything), a POST without or with a forged token is refused and
    changes nothing."""
    app = every_app
    admin = app.test_client()
    set_up(admin)
    checked = 0
    for url, endpoint in every_route(app, "POST"):
        if endpoint == "auth.setup":
            continue
        for data in ({}, {"csrf_token": "forged"}):
            audit = len(app.extensions["users"].audit_log())
            answer = admin.post(url, data=data)
            assert answer.status_code == 400 and "CSRF" in answer.get_data(as_text=True), url
            assert len(app.extensions["users"].audit_log()) == audit, url
        checked += 1
    assert checked >= 5
    with app.test_request_context():
        home = url_for(app.config["HOME"])
    assert admin.get(home).status_code == 200                     # still logged in: the logout was refused too


def test_the_first_start_page_needs_the_csrf_token_too(app):
    answer = app.test_client().post("/setup", data={"name": "x", "password": PASSWORD, "confirm": PASSWORD})
    assert answer.status_code == 400 and app.extensions["users"].count() == 0


def test_failed_logins_are_rate_limited_per_name(app):
    set_up(app.test_client())
    client = app.test_client()
    codes = [log_in(client, "admin.ward3", f"wrong password {n}").status_code for n in range(6)]
    assert codes == [401] * 5 + [429]
    assert log_in(client, "admin.ward3").status_code == 429          # even the right password, for now


def test_the_limiter_forgets_failures_after_its_window():
    limiter = LoginLimiter(pair_attempts=2, window_s=60.0)
    limiter.failed("a", "10.0.0.5", now=0.0)
    limiter.failed("a", "10.0.0.5", now=10.0)
    assert limiter.blocked_for_s("a", "10.0.0.5", now=20.0) == pytest.approx(40.0)
    assert limiter.blocked_for_s("a", "10.0.0.5", now=61.0) == 0.0


def test_passwords_are_stored_as_argon2id_hashes_only(tmp_path):
    users = UserStore(tmp_path / "webui.db")
    users.create("eng.smith", PASSWORD, "engineer", by="admin")
    raw = b"".join(p.read_bytes() for p in tmp_path.glob("webui.db*"))          # the file and its WAL
    assert PASSWORD.encode() not in raw and b"$argon2id$" in raw
    assert users.verify("eng.smith", PASSWORD).can("nurse") and not users.verify("eng.smith", PASSWORD).can("admin")
    assert users.verify("nobody", PASSWORD) is None
    with pytest.raises(AccountError, match="already exists"):
        users.create("eng.smith", PASSWORD, "nurse", by="admin")
    with pytest.raises(AccountError, match="role must be one of"):
        users.create("eng.jones", PASSWORD, "surgeon", by="admin")


def test_the_live_view_serves_the_monitors_snapshot_and_says_when_it_is_stale(app, tmp_path):
    client = app.test_client()
    set_up(client)
    assert client.get("/api/live").get_json()["stale"] is True               # nothing written yet
    live = LiveChannel(tmp_path / "live.json")
    live.publish({"bed_id": "bed-4", "time_s": 60.0, "sequence": 1, "frame_interval_s": 1.0,
                  "map": {"mmhg": [[0.0, 40.0]], "pixel_mm": [56, 56], "peak_kpa": 5.3}, "regions": [],
                  "alarms": [], "status": {"faults": 0}, "turn": {"due_in_s": 7000.0}})
    live.close()
    snapshot = client.get("/api/live").get_json()
    assert snapshot["bed_id"] == "bed-4" and snapshot["stale"] is False and snapshot["age_s"] < 3
    data = json.loads((tmp_path / "live.json").read_text())
    data["written_at"] = time.time() - 10
    (tmp_path / "live.json").write_text(json.dumps(data))
    assert client.get("/api/live").get_json()["stale"] is True


def test_before_the_first_map_the_live_view_shows_the_start_up_phase_with_a_progress_bar(app, tmp_path):
    client = app.test_client()
    set_up(client)
    live = LiveChannel(tmp_path / "live.json")
    live.publish({"starting": {"phase": "building the reconstruction model", "step": "meshing", "share": 0.4}})
    live.close()
    snapshot = client.get("/api/live").get_json()
    assert snapshot["starting"] == {"phase": "building the reconstruction model", "step": "meshing", "share": 0.4}
    assert snapshot["message"] == "the monitor is starting: building the reconstruction model"
    assert snapshot["stale"] is False and "map" not in snapshot     # starting as it should: no stale-data alarm
    page = client.get("/").get_data(as_text=True)
    assert re.search(r'<progress id="starting-bar" max="1" value="0"></progress>', page)
    data = json.loads((tmp_path / "live.json").read_text())
    data["written_at"] = time.time() - webui.live.STARTING_QUIET_S - 5   # no step of progress for too long
    (tmp_path / "live.json").write_text(json.dumps(data))
    assert client.get("/api/live").get_json()["stale"] is True


def test_a_failed_start_up_is_shown_stale_at_once_in_plain_words(app, tmp_path):
    client = app.test_client()
    set_up(client)
    live = LiveChannel(tmp_path / "live.json")
    live.publish({"starting": {"phase": "building the reconstruction model", "step": "done", "share": 0.8,
                               "failed": True}})
    live.close()
    snapshot = client.get("/api/live").get_json()
    assert snapshot["stale"] is True
    assert snapshot["message"] == ("the monitor could not start (building the reconstruction model): call the "
                                   "clinical engineer")


def test_the_stream_sends_each_new_snapshot(app, tmp_path):
    client = app.test_client()
    set_up(client)
    live = LiveChannel(tmp_path / "live.json")
    live.publish({"bed_id": "bed-4", "time_s": 1.0, "sequence": 7, "frame_interval_s": 1.0})
    live.close()
    answer = client.get("/api/live/stream")
    assert answer.mimetype == "text/event-stream"
    events = [json.loads(line[6:]) for line in answer.get_data(as_text=True).splitlines() if line.startswith("data: ")]
    assert [e["sequence"] for e in events] == [7]
    assert answer.get_data(as_text=True).startswith("retry: 1000")      # browsers reconnect at once when it ends


def test_every_stream_shares_one_read_of_each_snapshot(app, tmp_path, monkeypatch):
    import webui.live

    client = app.test_client()
    set_up(client)
    reads = []                                      # the streams' reads, after the pages of setting up
    monkeypatch.setattr(webui.live, "read_live", lambda path: reads.append(path) or read_live(path))
    live = LiveChannel(tmp_path / "live.json")
    live.publish({"bed_id": "bed-4", "time_s": 1.0, "sequence": 7, "frame_interval_s": 1.0})
    live.close()
    bodies = [client.get("/api/live/stream").get_data(as_text=True) for _ in range(3)]
    assert len(reads) == 1 and bodies[0] == bodies[1] == bodies[2] and '"sequence":7' in bodies[0]


def test_session_cookies_are_httponly_strict_and_secure_by_default(tmp_path):
    app = create_app(tmp_path)
    client = app.test_client()
    client.get("/setup")
    cookie = client.get_cookie("session")
    assert cookie.http_only and cookie.secure and cookie.same_site == "Strict"
    assert (tmp_path / "webui.key").stat().st_mode & 0o777 == 0o600


def test_a_nurse_acknowledges_an_alarm_of_the_running_monitor_and_sees_it_in_the_history(small_mat_calibration,
                                                                                          tmp_path):
    """The monitor daemon and the screen share a data directory, as on the appliance."""
    daemon, events, app, client = nurse_beside_a_monitor(small_mat_calibration, tmp_path)
    daemon.run(8)
    daemon.live.close()
    daemon.live = LiveChannel(tmp_path / "live.json")
    alarm = next(e for e in events if e.kind == "raised" and e.key.startswith("pressure:"))
    page = client.get("/alarms").get_data(as_text=True)
    assert "Acknowledge" in page and "sustained pressure" in page
    csrf = token(client, "/alarms")
    refused = client.post("/alarms/999/acknowledge", data={"csrf_token": csrf}, follow_redirects=True)
    assert "alarm 999 is not open: nothing was acknowledged" in refused.get_data(as_text=True)
    bad_pause = client.post("/alarms/pause-audio", data={"csrf_token": csrf, "minutes": "10"}, follow_redirects=True)
    assert "at most 2 minutes" in bad_pause.get_data(as_text=True)
    with Store.open(tmp_path / "appliance.db") as store:
        assert store.pending_commands() == []                                  # the refusals queued nothing
    answer = client.post(f"/alarms/{alarm.alarm_id}/acknowledge", data={"csrf_token": csrf})
    assert answer.status_code == 303
    daemon.run(1)
    daemon.close()
    acked = [e for e in events if e.kind == "acknowledged"]
    assert [(e.alarm_id, e.user) for e in acked] == [(alarm.alarm_id, "nurse.jones")]
    history = client.get("/alarms").get_data(as_text=True)
    assert "acknowledged" in history and "nurse.jones" in history
    assert client.get("/api/commands/1").get_json()["state"] == "done"
    assert ("nurse.jones", "acknowledged alarm") in [(e["user"], e["action"])
                                                     for e in app.extensions["users"].audit_log()]


@pytest.mark.parametrize("behind_proxy", [True, False])
def test_behind_the_proxy_the_limiter_counts_each_browser_not_the_proxy(tmp_path, behind_proxy):
    """Enough wrong passwords from one browser through the proxy to lock its address: another browser can still
    log in (and without trusting the proxy, as a check that the test can tell, it cannot)."""
    import threading
    import urllib.parse
    import urllib.request

    from waitress import create_server

    from webui.server import server_options

    app = create_app(tmp_path, secure_cookies=False)
    app.extensions["users"].create("nurse.jones", PASSWORD, "nurse", by="admin")
    server = create_server(app, **server_options("127.0.0.1", 0, threads=4, ident="test", behind_proxy=behind_proxy))
    threading.Thread(target=server.run, daemon=True).start()
    opener = urllib.request.build_opener(urllib.request.HTTPCookieProcessor())

    def log_in_from(address, name, password):
        base = f"http://127.0.0.1:{server.effective_port}"
        page = opener.open(urllib.request.Request(base + "/login", headers={"X-Forwarded-For": address})).read()
        csrf = re.search(rb'name="csrf_token" value="([^"]+)"', page).group(1).decode()
        form = urllib.parse.urlencode({"name": name, "password": password, "csrf_token": csrf}).encode()
        try:
            return opener.open(urllib.request.Request(base + "/login", data=form,
                                                      headers={"X-Forwarded-For": address})).status
        except urllib.error.HTTPError as error:
            return error.code
    try:
        guesses = [log_in_from("10.0.0.66", f"guess{n}", "wrong password!") for n in range(ADDRESS_ATTEMPTS)]
        assert guesses == [401] * ADDRESS_ATTEMPTS
        assert log_in_from("10.0.0.12", "nurse.jones", PASSWORD) == (200 if behind_proxy else 429)
    finally:
        server.task_dispatcher.shutdown(timeout=5)         # the workers first, so none writes to a closed server
        server.close()
    if behind_proxy:
        assert "from 10.0.0.12" in app.extensions["users"].audit_log()[0]["detail"]


def test_the_screen_loads_no_driver_and_no_simulator(tmp_path):
    code = ("import sys, webui, webui.__main__; webui.create_app(sys.argv[1]); "
            "print(sorted(m for m in sys.modules if m.startswith(('appliance.drivers', 'appliance.sim'))))")
    done = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, check=True,
                          timeout=120)
    assert done.stdout.strip() == "[]", done.stdout + done.stderr


def test_page_views_read_the_store_while_the_monitor_holds_its_write_lock(app):
    from appliance.store import StoreError
    from webui.alarms import reader

    nurse = client_as(app, "nurse")
    path = app.config["STORE_PATH"]
    Store.open(path).close()                              # the monitor made the store
    monitor = sqlite3.connect(path, isolation_level=None)
    monitor.execute("BEGIN IMMEDIATE")                    # and is inside a frame's commit
    try:
        for page in ("/alarms", "/history", "/patient", "/settings", "/api/settings"):
            assert nurse.get(page).status_code == 200, page
        with app.test_request_context(), reader() as s:
            with pytest.raises(StoreError, match="open read-only"):
                s.queue_command("acknowledge", {"alarm_id": 1}, "nurse.test")
            with pytest.raises(sqlite3.OperationalError, match="readonly database"):
                s._conn().execute("DELETE FROM commands")
    finally:
        monitor.execute("ROLLBACK")
        monitor.close()


def test_the_live_page_has_a_line_for_settings_that_are_not_the_default(app):
    page = client_as(app, "nurse").get("/").get_data(as_text=True)
    assert 'id="changed"' in page and "Not the default" in page
    answer = app.test_client().get("/static/live.js")
    assert "settings_changed" in answer.get_data(as_text=True)
    answer.close()
