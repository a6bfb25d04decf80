"""The screen against an attacker: redirects, sessions, passwords, login limits, audit size, headers, files, load.

Each test drives the app as a browser would (Flask's test client, or a real
waitress server where the server's own limits are the point) and none depends on
how fast the machine is.
"""

import http.client
import http.cookiejar
import os
import re
import socket
import stat
import threading
import urllib.parse
import urllib.request

import pytest
from webui_client import PASSWORD, client_as, log_in, set_up, token

from appliance.accounts.passwords import common_passwords
from appliance.accounts.users import MAX_AUDIT_USER, AccountError, UserStore
from webui import create_app
from webui.limiter import ADDRESS_ATTEMPTS, PAIR_ATTEMPTS, LoginLimiter

NEW = "staple battery horse"


@pytest.fixture
def app(tmp_path):
    return create_app(tmp_path, secure_cookies=False, TESTING=True, STREAM_MAX_S=1.0)


def from_address(app, address):
    """A test client whose requests come from ``address``."""
    client = app.test_client()
    client.environ_base["REMOTE_ADDR"] = address
    return client


def post(client, path, **data):
    return client.post(path, data={"csrf_token": token(client, "/account/password"), **data})


# -- the page after login ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("target", [
    "/\t/evil.example", "/\n/evil.example", "/\r\n/evil.example", "//evil.example", "/\\evil.example",
    "\\/evil.example", "/\\/evil.example", "https://evil.example/", "javascript:alert(1)", " //evil.example",
    "/\x00/evil.example", "evil.example", "",
])
def test_a_login_never_sends_the_browser_off_site(app, target):
    set_up(app.test_client())
    client = app.test_client()
    answer = client.post("/login", query_string={"next": target},
                         data={"name": "admin.ward3", "password": PASSWORD, "csrf_token": token(client)})
    assert answer.status_code == 302 and answer.headers["Location"] == "/"


def test_a_login_returns_to_the_local_page_asked_for(app):
    set_up(app.test_client())
    client = app.test_client()
    answer = client.post("/login", query_string={"next": "/history?hours=8"},
                         data={"name": "admin.ward3", "password": PASSWORD, "csrf_token": token(client)})
    assert answer.headers["Location"] == "/history?hours=8"


# -- sessions ------------------------------------------------------------------------------------------------------

def copy_of(app, client):
    """Another browser holding a copy of ``client``'s session cookie (as a thief would)."""
    thief = app.test_client()
    thief.set_cookie("session", client.get_cookie("session").value)
    return thief


def logged_in(client) -> bool:
    return client.get("/").status_code == 200


def log_out(client):
    return client.post("/logout", data={"csrf_token": token(client, "/account/password")})


def test_a_copied_cookie_stops_working_at_logout_but_other_sessions_of_the_user_go_on(app):
    nurse = client_as(app, "nurse", "nurse.jones")
    other_screen = app.test_client()
    log_in(other_screen, "nurse.jones")
    thief = copy_of(app, nurse)
    assert logged_in(thief)
    assert log_out(nurse).status_code == 302
    assert not logged_in(nurse) and not logged_in(thief)
    assert logged_in(other_screen)


def test_a_changed_password_ends_every_other_session_of_the_user(app):
    nurse = client_as(app, "nurse", "nurse.jones")
    other_screen = app.test_client()
    log_in(other_screen, "nurse.jones")
    thief = copy_of(app, nurse)
    assert post(nurse, "/account/password", current=PASSWORD, password=NEW, confirm=NEW).status_code == 303
    assert not logged_in(thief) and not logged_in(other_screen)
    page = nurse.get("/")                                           # the one who changed it goes on
    assert page.status_code == 200 and "your password was changed" in page.get_data(as_text=True)


def test_a_reset_by_an_admin_ends_every_session_of_the_user(app):
    admin = client_as(app, "admin", "admin.ward3")
    nurse = client_as(app, "nurse", "nurse.jones")
    assert post(admin, "/accounts/nurse.jones/password", password=NEW).status_code == 303
    assert not logged_in(nurse) and logged_in(admin)


def test_an_admin_who_resets_their_own_password_stays_logged_in_alone(app):
    admin = client_as(app, "admin", "admin.ward3")
    thief = copy_of(app, admin)
    assert post(admin, "/accounts/admin.ward3/password", password=NEW).status_code == 303
    assert logged_in(admin) and not logged_in(thief)


def test_an_account_made_again_under_a_removed_name_inherits_no_session(app):
    users = app.extensions["users"]
    nurse = client_as(app, "nurse", "nurse.jones")
    users.remove("nurse.jones", by="admin.ward3")
    users.create("nurse.jones", NEW, "engineer", by="admin.ward3")
    assert not logged_in(nurse)


# -- passwords -----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("password, message", [
    ("password123", "most common"),
    ("1234567890", "digits only"),
    ("98765432101234", "digits only"),
    ("qwertyuiop", "most common"),
    ("Letmein2024!", "most common"),
    ("PASSWORD!!!!", "most common"),
    ("zzzzzzzzzzzz", "one repeated character"),
    ("short one", "at least 10 characters"),
    ("nurse.jones rocks", "must not contain the user name"),
    ("my name is JONES ok", "must not contain the user name"),
])
def test_weak_passwords_are_refused_everywhere_with_the_reason(app, password, message):
    users = app.extensions["users"]
    with pytest.raises(AccountError, match=message):
        users.create("nurse.jones", password, "nurse", by="admin")
    fresh = create_app(app.config["LIVE_PATH"].parent / "fresh", secure_cookies=False, TESTING=True)
    client = fresh.test_client()
    first = client.post("/setup", data={"name": "nurse.jones", "password": password, "confirm": password,
                                         "csrf_token": token(client, "/setup")})
    assert first.status_code == 400 and message in first.get_data(as_text=True)
    admin = client_as(app, "admin", "admin.ward3")
    made = post(admin, "/accounts", name="nurse.jones", role="nurse", password=password, confirm=password)
    assert made.status_code == 400 and message in made.get_data(as_text=True)
    users.create("nurse.jones", PASSWORD, "nurse", by="admin.ward3")
    reset = post(admin, "/accounts/nurse.jones/password", password=password)
    assert reset.status_code == 400 and message in reset.get_data(as_text=True)
    nurse = client_as(app, "nurse", "nurse.jones")
    own = post(nurse, "/account/password", current=PASSWORD, password=password, confirm=password)
    assert own.status_code == 400 and message in own.get_data(as_text=True)
    assert users.verify("nurse.jones", PASSWORD)


def test_long_passphrases_pass_and_the_common_list_is_shipped():
    assert len(common_passwords()) >= 300 and {"123456", "password", "qwerty", "letmein"} <= common_passwords()
    from appliance.accounts.passwords import check
    for good in (PASSWORD, NEW, "Tuesday kettle 42", "blue mug on the ward"):
        check("nurse.jones", good)


# -- login limits --------------------------------------------------------------------------------------------------

def test_failures_from_one_address_lock_that_account_there_not_others_nor_other_addresses(app):
    users = app.extensions["users"]
    set_up(app.test_client())
    users.create("nurse.jones", PASSWORD, "nurse", by="admin.ward3")
    attacker = from_address(app, "10.0.0.66")
    codes = [log_in(attacker, "admin.ward3", f"guess number {n}").status_code for n in range(PAIR_ATTEMPTS + 1)]
    assert codes == [401] * PAIR_ATTEMPTS + [429]
    assert log_in(from_address(app, "10.0.0.66"), "nurse.jones").status_code == 302   # another account, same address
    assert log_in(from_address(app, "10.0.0.12"), "admin.ward3").status_code == 302   # same account, elsewhere
    assert log_in(app.test_client(), "admin.ward3").status_code == 302                # the bedside's own screen


def test_an_address_guessing_through_many_accounts_is_locked_for_all(app):
    set_up(app.test_client())
    attacker = from_address(app, "10.0.0.66")
    codes = [log_in(attacker, f"guess{n}", "wrong password!").status_code for n in range(ADDRESS_ATTEMPTS)]
    assert codes == [401] * ADDRESS_ATTEMPTS
    assert log_in(attacker, "admin.ward3").status_code == 429
    assert log_in(from_address(app, "10.0.0.12"), "admin.ward3").status_code == 302


def test_guesses_from_many_addresses_lock_the_account_but_never_on_the_bedside_screen(app):
    app.extensions["login_limiter"] = LoginLimiter(pair_attempts=2, address_attempts=3, account_attempts=4)
    set_up(app.test_client())
    for n in range(4):
        assert log_in(from_address(app, f"10.0.1.{n}"), "admin.ward3", "wrong password!").status_code == 401
    assert log_in(from_address(app, "10.0.2.1"), "admin.ward3").status_code == 429
    assert log_in(from_address(app, "127.0.0.1"), "admin.ward3").status_code == 302
    assert log_in(from_address(app, "::1"), "admin.ward3").status_code == 302
    actions = [e["action"] for e in app.extensions["users"].audit_log()]
    assert actions.count("login locked") == 1                        # once, not at every refused try


def test_logging_in_to_ones_own_account_does_not_wipe_ones_guesses_at_others():
    limiter = LoginLimiter(pair_attempts=5, address_attempts=3, account_attempts=50)
    for name in ("admin", "sister"):
        limiter.failed(name, "10.0.0.66", now=0.0)
    limiter.succeeded("intruder", "10.0.0.66")
    limiter.failed("matron", "10.0.0.66", now=1.0)
    assert limiter.blocked_for_s("intruder", "10.0.0.66", now=2.0) > 0


def test_the_limiter_forgets_addresses_and_names_it_no_longer_needs(monkeypatch):
    import webui.limiter

    monkeypatch.setattr(webui.limiter, "SWEEP_EVERY", 10)
    limiter = LoginLimiter(window_s=60.0)
    for n in range(9):
        limiter.failed(f"name{n}", f"10.0.0.{n}", now=0.0)
    limiter.failed("late", "10.0.9.9", now=100.0)                   # the tenth: the others are out of the window
    assert set(limiter._failures) == {("addr", "10.0.9.9"), ("pair", "late", "10.0.9.9"), ("account", "late")}


# -- audit log size ------------------------------------------------------------------------------------------------

def test_an_over_long_user_name_is_refused_at_once_and_logged_cut_short(app):
    set_up(app.test_client())
    client = from_address(app, "10.0.0.66")
    name = "x" * 200_000
    answer = client.post("/login", data={"name": name, "password": "whatever it is", "csrf_token": token(client)})
    assert answer.status_code == 400 and "at most 64 characters" in answer.get_data(as_text=True)
    assert name[:1000] not in answer.get_data(as_text=True)
    entry = app.extensions["users"].audit_log()[0]
    assert entry["action"] == "login failed" and len(entry["user"]) < MAX_AUDIT_USER + 30
    assert entry["user"].startswith("x" * MAX_AUDIT_USER) and entry["user"].endswith(f"(+{200_000 - 64} chars)")
    codes = {client.post("/login", data={"name": name, "password": "p", "csrf_token": token(client)}).status_code
             for _ in range(ADDRESS_ATTEMPTS)}
    assert codes == {400, 429}                                      # the address is limited like any guesser


def test_every_audit_entry_is_bounded(tmp_path):
    users = UserStore(tmp_path / "webui.db")
    users.audit("y" * 5000, "login failed", "z" * 50_000)
    entry = users.audit_log()[0]
    assert len(entry["user"]) < 100 and len(entry["detail"]) < 600 and entry["detail"].endswith("chars)")


# -- headers -------------------------------------------------------------------------------------------------------

def assert_hardened(answer):
    policy = answer.headers.get("Content-Security-Policy", "")
    assert "default-src 'self'" in policy and "frame-ancestors 'none'" in policy and "unsafe-inline" not in policy
    assert answer.headers["X-Frame-Options"] == "DENY"
    assert answer.headers["X-Content-Type-Options"] == "nosniff"
    assert answer.headers["Referrer-Policy"] in ("same-origin", "no-referrer")


def test_every_kind_of_response_carries_the_security_headers(app):
    anonymous = app.test_client()
    assert_hardened(anonymous.get("/setup"))
    set_up(anonymous)
    admin = app.test_client()
    for answer in (admin.get("/login"), admin.get("/"), admin.get("/api/live"), admin.get("/no/such/page"),
                   admin.post("/logout"), log_in(admin, "admin.ward3", "wrong password!")):
        assert_hardened(answer)
    log_in(admin, "admin.ward3")
    with admin.get("/static/style.css") as css:
        assert_hardened(css)
    for path in ("/", "/accounts", "/history/summary"):
        assert_hardened(admin.get(path))


INLINE = re.compile(r"<script(?![^>]*\bsrc=)[^>]*>|<style|\sstyle=|\son[a-z]+=|javascript:", re.IGNORECASE)


def test_no_page_has_inline_script_or_style_the_policy_would_block(app):
    admin = client_as(app, "admin", "admin.ward3")
    for rule in app.url_map.iter_rules():
        if "GET" not in rule.methods or rule.arguments or rule.endpoint == "static":
            continue
        answer = admin.get(rule.rule)
        if answer.mimetype == "text/html":
            page = answer.get_data(as_text=True)
            assert not INLINE.search(page), (rule.rule, INLINE.search(page).group(0))
        answer.close()
    for path in ("/setup", "/login"):
        assert not INLINE.search(app.test_client().get(path).get_data(as_text=True))


# -- files ---------------------------------------------------------------------------------------------------------

def mode(path):
    return stat.S_IMODE(path.stat().st_mode)


def test_the_accounts_database_and_the_session_key_are_made_owner_only(tmp_path):
    old = os.umask(0o022)
    try:
        app = create_app(tmp_path, secure_cookies=False, TESTING=True)
        set_up(app.test_client())
    finally:
        os.umask(old)
    files = sorted(p.name for p in tmp_path.glob("webui.*"))
    assert {"webui.db", "webui.key"} <= set(files)
    assert {name: mode(tmp_path / name) for name in files} == dict.fromkeys(files, 0o600)


def test_files_left_readable_by_an_older_version_are_narrowed_when_opened(tmp_path):
    create_app(tmp_path, secure_cookies=False, TESTING=True)
    for name in ("webui.db", "webui.key"):
        os.chmod(tmp_path / name, 0o644)
    create_app(tmp_path, secure_cookies=False, TESTING=True)
    assert mode(tmp_path / "webui.db") == mode(tmp_path / "webui.key") == 0o600


# -- streams and connections ---------------------------------------------------------------------------------------

def test_streams_beyond_the_limit_are_refused_with_retry_after_and_a_closed_one_frees_its_place(app):
    app.config["MAX_STREAMS"] = 2
    nurse = client_as(app, "nurse", "nurse.jones")
    first, second = nurse.get("/api/live/stream"), nurse.get("/api/live/stream")
    assert first.status_code == second.status_code == 200
    refused = nurse.get("/api/live/stream")
    assert refused.status_code == 503 and int(refused.headers["Retry-After"]) > 0
    assert nurse.get("/").status_code == 200                         # pages are still served
    first.close()
    third = nurse.get("/api/live/stream")
    assert third.status_code == 200
    second.close()
    third.close()


@pytest.fixture
def served(tmp_path, monkeypatch):
    """The screen on a real waitress with two worker threads, a nurse's session cookie, and the port."""
    import webui.streams
    from waitress import create_server

    from webui.server import server_options, stream_limit

    monkeypatch.setattr(webui.streams, "HEARTBEAT_S", 0.2)         # a closed stream frees its thread soon
    app = create_app(tmp_path, secure_cookies=False, STREAM_MAX_S=300.0, MAX_STREAMS=stream_limit(2))
    app.extensions["users"].create("nurse.jones", PASSWORD, "nurse", by="admin")
    server = create_server(app, **server_options("127.0.0.1", 0, threads=2, ident="test", behind_proxy=False))
    threading.Thread(target=server.run, daemon=True).start()
    port = server.effective_port
    jar = http.cookiejar.CookieJar()
    opener = urllib.request.build_opener(urllib.request.HTTPCookieProcessor(jar))
    page = opener.open(f"http://127.0.0.1:{port}/login", timeout=30).read()
    csrf = re.search(rb'name="csrf_token" value="([^"]+)"', page).group(1).decode()
    form = urllib.parse.urlencode({"name": "nurse.jones", "password": PASSWORD, "csrf_token": csrf}).encode()
    opener.open(f"http://127.0.0.1:{port}/login", data=form, timeout=30)
    session = "; ".join(f"{c.name}={c.value}" for c in jar)
    try:
        yield port, session
    finally:
        server.task_dispatcher.shutdown(timeout=5)
        server.close()


def get(port, path, cookie="", timeout_s=30.0):
    """The connection and the answer of GET ``path``; the connection stays open (a stream goes on)."""
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout_s)
    connection.request("GET", path, headers={"Cookie": cookie})
    answer = connection.getresponse()
    return connection, answer


def test_open_streams_leave_the_server_threads_for_pages(served):
    port, cookie = served
    connection, stream = get(port, "/api/live/stream", cookie)
    assert stream.status == 200 and stream.read(5) == b"retry"
    refused_connection, refused = get(port, "/api/live/stream", cookie)
    assert refused.status == 503 and refused.getheader("Retry-After")
    refused_connection.close()
    for path in ("/", "/api/live", "/login"):                       # the other thread still serves
        page_connection, page = get(port, path, cookie)
        assert page.status == 200
        page.read()
        page_connection.close()
    connection.close()


def test_a_hundred_and_fifty_idle_connections_do_not_shut_out_a_browser(served):
    port, cookie = served
    idle = [socket.create_connection(("127.0.0.1", port), timeout=30) for _ in range(150)]
    try:
        connection, page = get(port, "/login", timeout_s=20.0)
        assert page.status == 200 and b"Log in" in page.read()
        connection.close()
    finally:
        for s in idle:
            s.close()


def _first_start(app, base_url):
    """The first-start page and the answer to its form, both at ``base_url``."""
    client = app.test_client()
    page = client.get("/setup", base_url=base_url).get_data(as_text=True)
    sent = re.search(r'name="csrf_token" value="([^"]+)"', page).group(1)
    return page, client.post("/setup", base_url=base_url, data={"name": "admin.ward3", "password": PASSWORD,
                                                                 "confirm": PASSWORD, "csrf_token": sent})


def test_over_plain_http_from_another_machine_the_screen_says_logging_in_needs_https(tmp_path):
    app = create_app(tmp_path, TESTING=True)                       # Secure cookies, as the appliance serves it
    page = app.test_client().get("/setup", base_url="http://bed-4.ward3.example").get_data(as_text=True)
    assert "logging in needs HTTPS" in page and "https://bed-4.ward3.example/" in page     # before anyone types
    sent = re.search(r'name="csrf_token" value="([^"]+)"', page).group(1)
    # A browser keeps no Secure cookie from plain HTTP, so the form comes back without the session it needs.
    answer = app.test_client().post("/setup", base_url="http://bed-4.ward3.example",
                                    data={"name": "admin.ward3", "password": PASSWORD, "confirm": PASSWORD,
                                          "csrf_token": sent})
    assert answer.status_code == 400
    said = answer.get_data(as_text=True)
    assert "logging in needs HTTPS" in said and "CSRF" not in said      # ...and the reason given is the real one
    assert app.extensions["users"].count() == 0


@pytest.mark.parametrize("base_url", ["https://bed-4.ward3.example", "http://127.0.0.1:8080", "http://localhost"])
def test_over_https_or_on_the_machine_itself_the_first_start_works_with_no_https_notice(tmp_path, base_url):
    app = create_app(tmp_path, TESTING=True)
    page, answer = _first_start(app, base_url)
    assert "needs HTTPS" not in page
    assert answer.status_code == 302 and app.extensions["users"].count() == 1


def test_with_plain_http_chosen_no_https_notice_is_shown(tmp_path):
    app = create_app(tmp_path, secure_cookies=False, TESTING=True)
    page, answer = _first_start(app, "http://bed-4.ward3.example")
    assert "needs HTTPS" not in page and answer.status_code == 302
