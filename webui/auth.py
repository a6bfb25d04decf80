"""First start, login and logout.

There is no default password: while no account exists, every page leads to
``/setup``, where the first admin is made; afterwards ``/setup`` is gone. Failed
logins are limited per account and address (:mod:`webui.limiter`), and every
login, logout and failure is in the audit log. A user name longer than any
account's is refused at once, before it costs a password hash or a long audit
entry. After a login the browser goes back to the page it asked for, if that is
on this screen (:mod:`webui.redirects`).
"""

from __future__ import annotations

from flask import Blueprint, current_app, flash, g, redirect, render_template, request, session, url_for

from appliance.accounts.users import AccountError
from webui.redirects import local_path

MAX_NAME_CHARS = 64         # account names have at most 32; more is not a typing slip

bp = Blueprint("auth", __name__)


@bp.route("/setup", methods=["GET", "POST"])
def setup():
    users = current_app.extensions["users"]
    if users.count() > 0:
        return redirect(url_for("auth.login"))
    if request.method == "POST":
        name, password = request.form.get("name", "").strip(), request.form.get("password", "")
        if password != request.form.get("confirm", ""):
            flash("the two passwords differ", "error")
            return render_template("setup.html", name=name[:MAX_NAME_CHARS]), 400
        try:
            user = users.create(name, password, "admin", by="first start")
        except AccountError as exc:
            flash(str(exc), "error")
            return render_template("setup.html", name=name[:MAX_NAME_CHARS]), 400
        log_in(user.name)
        return redirect(url_for(current_app.config["HOME"]))
    return render_template("setup.html", name="")


@bp.route("/login", methods=["GET", "POST"])
def login():
    users, limiter = current_app.extensions["users"], current_app.extensions["login_limiter"]
    if users.count() == 0:
        return redirect(url_for("auth.setup"))
    if request.method == "POST":
        name, password = request.form.get("name", "").strip(), request.form.get("password", "")
        address = request.remote_addr
        too_long = len(name) > MAX_NAME_CHARS
        wait = limiter.blocked_for_s(None if too_long else name, address)
        if wait > 0:
            flash(f"too many failed logins: try again in {max(wait / 60, 1):.0f} min", "error")
            return render_template("login.html", name=name[:MAX_NAME_CHARS]), 429
        if too_long:
            _failed(None, name, f"a user name of {len(name)} characters, from {address}")
            flash(f"a user name has at most {MAX_NAME_CHARS} characters", "error")
            return render_template("login.html", name=""), 400
        user = users.verify(name, password)
        if user is None:
            _failed(name, name or "-", f"from {address}")
            flash("wrong user name or password", "error")
            return render_template("login.html", name=name), 401
        limiter.succeeded(name, address)
        log_in(user.name)
        return redirect(local_path(request.args.get("next")) or url_for(current_app.config["HOME"]))
    return render_template("login.html", name="")


@bp.route("/logout", methods=["POST"])
def logout():
    current_app.extensions["users"].audit(g.user.name, "logged out")
    current_app.extensions["sessions"].close(session["sid"])
    session.clear()
    return redirect(url_for("auth.login"))


def log_in(name: str) -> None:
    """A fresh session (no fixation): a new server-side session of ``name`` and, on first use, a new CSRF token."""
    session.clear()
    session["sid"] = current_app.extensions["sessions"].open(name)
    session.permanent = True
    current_app.extensions["users"].audit(name, "logged in", f"from {request.remote_addr}")


def _failed(name: str | None, shown: str, detail: str) -> None:
    """Count a failed login (``name`` None: for the address alone) and audit it; a lock it causes is audited too."""
    users, limiter = current_app.extensions["users"], current_app.extensions["login_limiter"]
    users.audit(shown, "login failed", detail)
    if limiter.failed(name, request.remote_addr):
        users.audit(shown, "login locked", f"too many failures, from {request.remote_addr}: further tries are "
                                           f"refused for a while and not logged one by one")
