"""Accounts: an admin adds, re-roles and removes users and resets passwords; everyone changes their own.

There are no shared logins on a ward: each nurse and engineer has an account, so
the audit log says who acknowledged what. Every change here is audited (by
:class:`appliance.accounts.users.UserStore`), and a refused change says why and changes
nothing. A removed or re-roled user's next request already sees the change,
because the guard reads the account on every request. A new password ends
every session of its account; the user who set their own stays logged in, in a
new session.
"""

from __future__ import annotations

from flask import Blueprint, current_app, flash, g, redirect, render_template, request, url_for

from appliance.accounts.users import ROLES, AccountError, UserStore
from webui.clocks import clock
from webui.auth import log_in
from webui.security import requires

bp = Blueprint("accounts", __name__)


def users() -> UserStore:
    return current_app.extensions["users"]


@bp.route("/accounts")
@requires("admin")
def page():
    return render_template("accounts.html", users=users().users(), roles=ROLES, audit=users().audit_log(),
                           clock=clock)


@bp.route("/accounts", methods=["POST"])
@requires("admin")
def create():
    form = request.form
    name = form.get("name", "").strip()

    def make():
        if form.get("password", "") != form.get("confirm", ""):
            raise AccountError("the two passwords differ")
        users().create(name, form.get("password", ""), form.get("role", ""), by=g.user.name)
        return f"account {name} ({form['role']}) created"
    return _change(make)


@bp.route("/accounts/<name>/role", methods=["POST"])
@requires("admin")
def set_role(name: str):
    role = request.form.get("role", "")

    def change():
        users().set_role(name, role, by=g.user.name)
        return f"{name} is now {role}"
    return _change(change)


@bp.route("/accounts/<name>/password", methods=["POST"])
@requires("admin")
def reset_password(name: str):
    password = request.form.get("password", "")

    def reset():
        users().set_password(name, password, by=g.user.name)
        if name == g.user.name:
            log_in(name)
        return f"{name}'s password was reset"
    return _change(reset)


@bp.route("/accounts/<name>/remove", methods=["POST"])
@requires("admin")
def remove(name: str):
    def change():
        users().remove(name, by=g.user.name)
        return f"account {name} removed"
    return _change(change)


@bp.route("/account/password", methods=["GET", "POST"])
def own_password():
    if request.method == "GET":
        return render_template("password.html")
    form = request.form
    if users().verify(g.user.name, form.get("current", "")) is None:
        flash("the current password is wrong: nothing was changed", "error")
        return render_template("password.html"), 400
    if form.get("password", "") != form.get("confirm", ""):
        flash("the two new passwords differ: nothing was changed", "error")
        return render_template("password.html"), 400
    try:
        users().set_password(g.user.name, form.get("password", ""), by=g.user.name)
    except AccountError as exc:
        flash(f"{exc}: nothing was changed", "error")
        return render_template("password.html"), 400
    log_in(g.user.name)
    flash("your password was changed", "info")
    return redirect(url_for(current_app.config["HOME"])), 303


def _change(change):
    """Run ``change`` (returns the message to show); an AccountError re-shows the page with its reason, 400."""
    try:
        message = change()
    except AccountError as exc:
        flash(f"{exc}: nothing was changed", "error")
        return page(), 400
    flash(message, "info")
    return redirect(url_for("accounts.page")), 303
