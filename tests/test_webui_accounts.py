"""Accounts: an admin manages users; everyone changes their own password; refusals change nothing."""

import pytest

from webui import create_app
from webui_client import PASSWORD, client_as, log_in, token

NEW = "staple battery horse"


@pytest.fixture
def app(tmp_path):
    return create_app(tmp_path, secure_cookies=False, TESTING=True)


def post(client, path, **data):
    return client.post(path, data={"csrf_token": token(client, "/account/password"), **data})


def test_an_admin_creates_re_roles_resets_and_removes_an_account(app):
    admin, users = client_as(app, "admin", "admin.ward3"), app.extensions["users"]
    answer = post(admin, "/accounts", name="nurse.jones", role="nurse", password=NEW, confirm=NEW)
    assert answer.status_code == 303 and users.get("nurse.jones").role == "nurse"
    assert post(admin, "/accounts/nurse.jones/role", role="engineer").status_code == 303
    assert users.get("nurse.jones").role == "engineer"
    assert post(admin, "/accounts/nurse.jones/password", password="another long one").status_code == 303
    assert users.verify("nurse.jones", "another long one") and not users.verify("nurse.jones", NEW)
    assert post(admin, "/accounts/nurse.jones/remove").status_code == 303
    assert users.get("nurse.jones") is None
    actions = [(e["user"], e["action"]) for e in users.audit_log()]
    for action in ("account created", "role changed", "password changed", "account removed"):
        assert ("admin.ward3", action) in actions


@pytest.mark.parametrize("path, data, message", [
    ("/accounts", {"name": "Nurse Jones", "role": "nurse", "password": NEW, "confirm": NEW}, "a user name is"),
    ("/accounts", {"name": "nurse.b", "role": "matron", "password": NEW, "confirm": NEW}, "role must be one of"),
    ("/accounts", {"name": "nurse.b", "role": "nurse", "password": "short", "confirm": "short"}, "at least 10"),
    ("/accounts", {"name": "nurse.b", "role": "nurse", "password": NEW, "confirm": NEW + "!"}, "passwords differ"),
    ("/accounts", {"name": "admin.ward3", "role": "nurse", "password": NEW, "confirm": NEW}, "already exists"),
    ("/accounts/admin.ward3/role", {"role": "nurse"}, "the last admin"),
    ("/accounts/admin.ward3/remove", {}, "your own account"),
    ("/accounts/nobody/role", {"role": "nurse"}, "there is no user"),
    ("/accounts/nobody/password", {"password": NEW}, "there is no user"),
    ("/accounts/admin.ward3/password", {"password": "admin.ward3"}, "must not contain the user name"),
])
def test_a_refused_account_change_says_why_and_changes_nothing(app, path, data, message):
    admin, users = client_as(app, "admin", "admin.ward3"), app.extensions["users"]
    before = (users.users(), len(users.audit_log()))
    answer = post(admin, path, **data)
    assert answer.status_code == 400
    assert message in answer.get_data(as_text=True) and "nothing was changed" in answer.get_data(as_text=True)
    assert (users.users(), len(users.audit_log())) == before
    assert users.verify("admin.ward3", PASSWORD)


def test_the_last_admin_can_be_removed_by_another_admin_only_when_one_remains(app):
    admin, users = client_as(app, "admin", "admin.ward3"), app.extensions["users"]
    users.create("admin.two", PASSWORD, "admin", by="admin.ward3")
    assert post(admin, "/accounts/admin.two/remove").status_code == 303
    assert [u.name for u in users.users()] == ["admin.ward3"]


@pytest.mark.parametrize("role", ["nurse", "engineer"])
def test_only_admins_manage_accounts(app, role):
    client, users = client_as(app, role), app.extensions["users"]
    assert client.get("/accounts").status_code == 403
    assert post(client, "/accounts", name="x.y", role="admin", password=NEW, confirm=NEW).status_code == 403
    assert post(client, "/accounts/admin.ward3/role", role="nurse").status_code == 403
    assert users.get("x.y") is None and users.get("admin.ward3").role == "admin"


def test_a_user_changes_their_own_password_only_with_the_current_one(app):
    nurse, users = client_as(app, "nurse", "nurse.jones"), app.extensions["users"]
    wrong = post(nurse, "/account/password", current="not it at all", password=NEW, confirm=NEW)
    assert wrong.status_code == 400 and "current password is wrong" in wrong.get_data(as_text=True)
    differ = post(nurse, "/account/password", current=PASSWORD, password=NEW, confirm=NEW + "x")
    assert differ.status_code == 400 and "differ" in differ.get_data(as_text=True)
    assert users.verify("nurse.jones", PASSWORD)
    assert post(nurse, "/account/password", current=PASSWORD, password=NEW, confirm=NEW).status_code == 303
    assert users.verify("nurse.jones", NEW) and not users.verify("nurse.jones", PASSWORD)
    assert log_in(app.test_client(), "nurse.jones", NEW).status_code == 302


def test_a_removed_user_is_logged_out_at_the_next_request(app):
    nurse = client_as(app, "nurse", "nurse.jones")
    assert nurse.get("/").status_code == 200
    app.extensions["users"].remove("nurse.jones", by="admin.ward3")
    assert nurse.get("/").headers["Location"].startswith("/login")
