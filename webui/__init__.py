"""The nurse's screen: a Flask app beside the monitor daemon, reading its live view and store.

``create_app(data_dir)`` is the app factory (the monitor's data directory: its
``live.json`` and ``appliance.db``, and ``webui.db`` with the accounts and audit
log). ``create_ward_app`` makes the ward station's screen from the same parts:
its own accounts, and the ward page instead of one bed's; ``create_hospital_app`` the
hospital overview, from the history in PostgreSQL. The session key
is made once and kept in ``webui.key`` (mode 0600) so a restart does not log
everyone out. Cookies are HttpOnly, SameSite=Strict and, unless ``secure_cookies``
is turned off for plain-HTTP tests, Secure; they name a session kept on the
server (:mod:`webui.sessions`), which logout and a new password end. Every
response carries the headers of :mod:`webui.headers`.
"""

from __future__ import annotations

import secrets
from datetime import timedelta
from pathlib import Path

from flask import Flask, current_app, g, redirect, url_for

from appliance.accounts.private import private_file
from appliance.accounts.users import UserStore
from appliance.alerts.wording import alarm_words, setting_words
from webui import accounts, alarms, auth, charting, engineering, fhir, history, live, patient, report, settings, ward
from webui.headers import add_security_headers
from webui.limiter import LoginLimiter
from webui.security import csrf_token, guard, needs_https
from webui.sessions import SessionStore

SESSION_HOURS = 12          # one shift
BLUEPRINTS = (auth.bp, accounts.bp, live.bp, alarms.bp, patient.bp, history.bp, report.bp, settings.bp,
              engineering.bp, charting.bp, fhir.bp)
WARD_BLUEPRINTS = (auth.bp, accounts.bp, ward.bp)
PAGES = (("hospital.page", "Hospital", "nurse"), ("ward.page", "Ward", "nurse"), ("live.page", "Live", "nurse"),
         ("alarms.page", "Alarms", "nurse"),
         ("patient.page", "Patient", "nurse"), ("history.page", "History", "nurse"),
         ("settings.page", "Settings", "nurse"), ("engineering.page", "Engineering", "engineer"),
         ("charting.page", "Charting", "admin"), ("accounts.page", "Accounts", "admin"))
"""The header's links, in order: each shown when its blueprint is registered and the user's role allows it."""


def create_app(data_dir, *, secure_cookies: bool = True, blueprints=BLUEPRINTS, **config) -> Flask:
    """``config`` adds to Flask's; ``HOME`` is the endpoint a login leads to (default the live view)."""
    data_dir = Path(data_dir)
    data_dir.mkdir(parents=True, exist_ok=True)
    app = Flask(__name__)
    app.config.update(SECRET_KEY=_secret_key(data_dir / "webui.key"), LIVE_PATH=data_dir / "live.json",
                      STORE_PATH=data_dir / "appliance.db",
                      SESSION_COOKIE_HTTPONLY=True, SESSION_COOKIE_SAMESITE="Strict",
                      SESSION_COOKIE_SECURE=secure_cookies,
                      PERMANENT_SESSION_LIFETIME=timedelta(hours=SESSION_HOURS), HOME="live.page")
    app.config.update(config)
    app.extensions["users"] = UserStore(data_dir / "webui.db")
    app.extensions["sessions"] = SessionStore(data_dir / "webui.db",
                                              app.config["PERMANENT_SESSION_LIFETIME"].total_seconds())
    app.extensions["login_limiter"] = LoginLimiter()
    app.before_request(guard)
    app.after_request(add_security_headers)
    app.jinja_env.globals.update(csrf_token=csrf_token, nav_links=nav_links, needs_https=needs_https,
                                 simulated_banner=live.simulated_banner, simulated_texts=live.SIMULATED)
    app.jinja_env.filters.update(alarm_words=alarm_words, setting_words=setting_words)
    for blueprint in blueprints:
        app.register_blueprint(blueprint)
    return app


def create_ward_app(data_dir, station, ward_config, *, secure_cookies: bool = True, **config) -> Flask:
    """The ward station's screen for a running ``WardStation``; accounts in ``data_dir`` (the station's own). With
    a ``[history]`` in ``ward_config`` it reads the hospital history too, at most every ``HISTORY_REFRESH_S``
    (Flask config; default ``webui.ward_history.REFRESH_S``): imported only then, as it needs the PostgreSQL
    driver."""
    app = create_app(data_dir, secure_cookies=secure_cookies, blueprints=WARD_BLUEPRINTS, HOME="ward.page",
                     WARD=ward_config, **config)
    app.extensions["ward_station"] = station
    if ward_config.history is not None:
        from appliance.hospital.history.reads import connector
        from webui import ward_history

        source = ward_config.history
        app.extensions["ward_history"] = ward_history.WardHistory(
            connector(source.dsn), source.ward, source.look_back_h,
            refresh_s=app.config.get("HISTORY_REFRESH_S", ward_history.REFRESH_S))
        app.register_blueprint(ward_history.bp)
    app.add_url_rule("/", "home", lambda: redirect(url_for("ward.page")))
    return app


def create_hospital_app(data_dir, hospital, connect, *, secure_cookies: bool = True, **config) -> Flask:
    """The hospital overview for ``hospital`` (its description), reading the history through ``connect()`` (a new
    PostgreSQL connection, used as a context manager); accounts in ``data_dir``. Imported here, not above: the
    overview needs the ``hospital`` extra's PostgreSQL driver, which a bed's screen does without."""
    from webui import hospital as overview

    app = create_app(data_dir, secure_cookies=secure_cookies, blueprints=(auth.bp, accounts.bp, overview.bp),
                     HOME="hospital.page", **config)
    app.extensions.update(hospital=hospital, history=connect)
    app.add_url_rule("/", "home", lambda: redirect(url_for("hospital.page")))
    return app


def nav_links() -> list[tuple[str, str]]:
    """(endpoint, label) of the pages the logged-in user may open."""
    user = g.get("user")
    return [(endpoint, label) for endpoint, label, role in PAGES
            if endpoint in current_app.view_functions and user is not None and user.can(role)]


def _secret_key(path: Path) -> bytes:
    """The key in ``path``, made (32 random bytes) the first time; owner-only, also if it was made readable."""
    if not path.exists() or path.stat().st_size == 0:
        private_file(path).write_bytes(secrets.token_bytes(32))
    return private_file(path).read_bytes()
