"""The screen against an attacker: redirects, sessions, passwords, login limits, audit size, headers, files, load.

Each test drives the app as a browser would (Flask's test client, or a real
waitress server where the server's own limits are the point) and none depends on
how fast the machine is.
"""

import os
import re
import stat

import pytest
from webui_client import PASSWORD, client_as, log_in, set_up, token

from webui import create_app
from webui.passwords import common_passwords
from webui.users import AccountError

NEW = "staple battery horse"


@pytest.fixture
def app(tmp_path):
    return create_app(tmp_path, secure_cookies=False, TESTING=True, STREAM_MAX_S=1.0)


def post(client, path, **data):
    return client.post(path, data={"csrf_token": token(client, "/account/password"), **data})


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
    from webui.passwords import check
    for good in (PASSWORD, NEW, "Tuesday kettle 42", "blue mug on the ward"):
        check("nurse.jones", good)


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
    assert {name: mode(tmp_path / name) for name in files} == {name: 0o600 for name in files}


def test_files_left_readable_by_an_older_version_are_narrowed_when_opened(tmp_path):
    create_app(tmp_path, secure_cookies=False, TESTING=True)
    for name in ("webui.db", "webui.key"):
        os.chmod(tmp_path / name, 0o644)
    create_app(tmp_path, secure_cookies=False, TESTING=True)
    assert mode(tmp_path / "webui.db") == mode(tmp_path / "webui.key") == 0o600
