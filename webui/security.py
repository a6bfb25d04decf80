"""Login, roles and CSRF tokens for every blueprint.

Everything but the login and first-start pages and static files needs a login
(``before_request``): a session still open in :class:`webui.sessions.SessionStore`,
so a logged-out or superseded cookie counts as none. Routes that need more than a
nurse say so with :func:`requires`. Every state-changing request carries the
session's CSRF token (form field ``csrf_token`` or header ``X-CSRF-Token``),
compared in constant time. Failed logins are limited by :mod:`webui.limiter`.
"""

from __future__ import annotations

import functools
import secrets

from flask import abort, current_app, g, redirect, request, session, url_for
from werkzeug.wrappers import Response

from appliance.accounts.users import User

PUBLIC_ENDPOINTS = {"auth.login", "auth.setup", "static"}
STATE_CHANGING = {"POST", "PUT", "PATCH", "DELETE"}
LOOPBACK_HOSTS = {"localhost", "127.0.0.1", "[::1]"}
"""Where browsers keep Secure cookies over plain HTTP (a page on the machine itself is a secure context)."""
NEEDS_HTTPS = ("logging in needs HTTPS: this page came over plain HTTP, where the browser drops the screen's "
               "Secure session cookie. Open it as https://{host}/ (on the appliance, plain HTTP is redirected "
               "there); on a trusted test network the screen can be started with --plain-http")


def needs_https() -> str | None:
    """Why logging in cannot work over this connection, or None when the session cookie will be kept."""
    if not current_app.config.get("SESSION_COOKIE_SECURE") or request.is_secure:
        return None
    host = request.host.rsplit(":", 1)[0] if not request.host.endswith("]") else request.host
    return None if host in LOOPBACK_HOSTS else NEEDS_HTTPS.format(host=host)


def csrf_token() -> str:
    """The session's CSRF token, made on first use."""
    if "csrf" not in session:
        session["csrf"] = secrets.token_urlsafe(32)
    return session["csrf"]


def guard() -> Response | None:
    """``before_request``: CSRF on state changes, then a login for all but the public pages."""
    if request.method in STATE_CHANGING:
        sent = request.form.get("csrf_token") or request.headers.get("X-CSRF-Token") or ""
        if not session.get("csrf") or not secrets.compare_digest(sent, session["csrf"]):
            abort(400, description=needs_https() or "missing or wrong CSRF token: reload the page and try again")
    users = current_app.extensions["users"]
    token = session.get("sid")
    g.user = current_app.extensions["sessions"].user(token) if token else None
    if request.endpoint in PUBLIC_ENDPOINTS or request.blueprint == "fhir":   # the FHIR API checks its own tokens
        return None
    if users.count() == 0:
        return redirect(url_for("auth.setup"))
    if g.user is None:
        if request.path.startswith("/api/"):
            abort(401, description="log in first")
        return redirect(url_for("auth.login", next=request.path))
    return None


def requires(role: str):
    """A view only users with at least ``role`` may call (403 for the others)."""
    def wrap(view):
        @functools.wraps(view)
        def checked(*args, **kwargs):
            user: User | None = g.get("user")
            if user is None or not user.can(role):
                abort(403, description=f"this needs the {role} role")
            return view(*args, **kwargs)
        return checked
    return wrap
