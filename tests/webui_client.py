"""Driving the web screen with Flask's test client: the first admin, logins and CSRF tokens."""

import re

PASSWORD = "correct horse battery"


def token(client, path="/login"):
    """The CSRF token a page at ``path`` carries in its forms."""
    page = client.get(path).get_data(as_text=True)
    return re.search(r'name="csrf_token" value="([^"]+)"', page).group(1)


def set_up(client, name="admin.ward3"):
    """Make the first admin through /setup (it logs that client in)."""
    return client.post("/setup", data={"name": name, "password": PASSWORD, "confirm": PASSWORD,
                                       "csrf_token": token(client, "/setup")})


def log_in(client, name, password=PASSWORD):
    return client.post("/login", data={"name": name, "password": password, "csrf_token": token(client)})


def client_as(app, role, name=None):
    """A test client logged in with ``role`` (nurse, engineer or admin); the first admin is made if needed."""
    if app.extensions["users"].count() == 0:
        set_up(app.test_client())
    name = name or f"{role}.test"
    if app.extensions["users"].get(name) is None:
        app.extensions["users"].create(name, PASSWORD, role, by="admin.ward3")
    client = app.test_client()
    log_in(client, name)
    return client


def nurse_beside_a_monitor(calibration, data_dir):
    """A small monitor daemon (alarms at dose 0.05) and its screen on one data folder, with nurse.jones logged
    in: (daemon, the events it records, the app, the nurse's client)."""
    from test_daemon import FlakySource, small_daemon
    from webui import create_app

    daemon, events = small_daemon(calibration, data_dir, FlakySource(failing=()), alarm_dose=0.05)
    app = create_app(data_dir, secure_cookies=False, TESTING=True)
    set_up(app.test_client())
    app.extensions["users"].create("nurse.jones", PASSWORD, "nurse", by="admin.ward3")
    client = app.test_client()
    log_in(client, "nurse.jones")
    return daemon, events, app, client
