"""First start, login and logout.

There is no default password: while no account exists, every page leads to
``/setup``, where the first admin is made; afterwards ``/setup`` is gone. Failed
logins are limited per user name and per address, and every login, logout and
failure is in the audit log.
"""

from __future__ import annotations

from flask import Blueprint, current_app, flash, g, redirect, render_template, request, session, url_for

from webui.users import AccountError

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
            return render_template("setup.html", name=name), 400
        try:
            user = users.create(name, password, "admin", by="first start")
        except AccountError as exc:
            flash(str(exc), "error")
            return render_template("setup.html", name=name), 400
        _log_in(user.name)
        return redirect(url_for(current_app.config["HOME"]))
    return render_template("setup.html", name="")


@bp.route("/login", methods=["GET", "POST"])
def login():
    users, limiter = current_app.extensions["users"], current_app.extensions["login_limiter"]
    if users.count() == 0:
        return redirect(url_for("auth.setup"))
    if request.method == "POST":
        name, password = request.form.get("name", "").strip(), request.form.get("password", "")
        keys = (f"user:{name}", f"addr:{request.remote_addr}")
        wait = limiter.blocked_for_s(*keys)
        if wait > 0:
            users.audit(name or "-", "login refused", f"rate limited, from {request.remote_addr}")
            flash(f"too many failed logins: try again in {wait / 60:.0f} min", "error")
            return render_template("login.html", name=name), 429
        user = users.verify(name, password)
        if user is None:
            limiter.failed(*keys)
            users.audit(name or "-", "login failed", f"from {request.remote_addr}")
            flash("wrong user name or password", "error")
            return render_template("login.html", name=name), 401
        limiter.succeeded(*keys)
        _log_in(user.name)
        target = request.args.get("next", "")
        safe = target.startswith("/") and not target.startswith("//")
        return redirect(target if safe else url_for(current_app.config["HOME"]))
    return render_template("login.html", name="")


@bp.route("/logout", methods=["POST"])
def logout():
    current_app.extensions["users"].audit(g.user.name, "logged out")
    session.clear()
    return redirect(url_for("auth.login"))


def _log_in(name: str) -> None:
    """A fresh session (no fixation), holding only the user's name and a new CSRF token."""
    session.clear()
    session["user"] = name
    session.permanent = True
    current_app.extensions["users"].audit(name, "logged in", f"from {request.remote_addr}")
