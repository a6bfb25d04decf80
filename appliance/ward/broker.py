"""The ward broker's logins and ACL: each bed may publish only on its own topics, so none can speak for another.

Without them any client can publish on any bed's topics, and one retained "all quiet" summary on a bed's
topic hides that bed's alarms from the ward station. ``write_ward_broker`` writes, from the ward's bed ids
and station user names, into one folder:

- ``passwords``: Mosquitto's ``password_file``, one PBKDF2-SHA512 line per user in the format
  ``mosquitto_passwd`` writes (``user:$7$<iterations>$<base64 salt>$<base64 hash>``);
- ``secrets/<user>.password``: each user's random password on the first line, for the bed's
  ``[notify.mqtt] password_file`` or the station's ``[broker] password_file`` (folder 0700, files 0600);
- ``acl``: Mosquitto's ``acl_file``. A bed's user name is its bed id; it writes only
  ``<prefix>/<bed_id>/{alarm,turn,episode,status,summary,command-result}`` and reads only
  ``<prefix>/<bed_id>/{confirm,command}``. A station reads those topics of every bed and writes every bed's
  ``confirm`` and ``command``, nothing else;
- ``ward-broker.conf``: the lines for ``/etc/mosquitto/conf.d`` that name the two files, refuse anonymous
  clients and keep the station's queued alarms over a broker restart.

Running it again with more or fewer beds keeps every existing password and adds or removes users. Mosquitto
re-reads ``password_file`` and ``acl_file`` on SIGHUP (``systemctl reload mosquitto``), so a bed is added or
removed without a restart; connected clients stay connected.

Mosquitto reads both files after it has dropped root for its own user (``mosquitto`` on Debian), at start
and on every reload, so they must be that user's: ``broker_user`` gives them to it, and a later run without
it keeps the owner the files had.
"""

from __future__ import annotations

import base64
import hashlib
import os
import pwd
import secrets
import unicodedata
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from appliance.alerts.events import EVENT_TYPES
from appliance.alerts.ward_commands import COMMAND_TOPIC, RESULT_TOPIC
from appliance.errors import ConfigError
from appliance.files import read_secret, write_atomic

BED_TOPICS = (*EVENT_TYPES, "status", "summary", RESULT_TOPIC)
"""What a bed publishes under ``<prefix>/<bed_id>/`` (appliance.alerts.wardlink): the ACL lets it write these."""

CONFIRM_TOPIC = "confirm"
"""Written by the ward station under ``<prefix>/<bed_id>/`` to confirm each alarm event; read by that bed alone."""
STATION_TOPICS = (CONFIRM_TOPIC, COMMAND_TOPIC)
"""What a station writes under each ``<prefix>/<bed_id>/``: confirmations, and its nurses' commands."""

PBKDF2_ITERATIONS = 101
"""mosquitto_passwd's own count. The passwords are 192 random bits, which no count of iterations makes harder
to guess, while every login of every bed costs the broker this many rounds."""

SALT_BYTES = 12
PASSWORD_BYTES = 24
MAX_NAME = 64
FORBIDDEN_IN_NAMES = "/+#:"
"""'/', '+' and '#' would make a bed's ``%u`` in the ACL span topics or match others; ':' ends the user name in
the password file."""


@dataclass(frozen=True)
class Listener:
    """A listener for the conf snippet: ``port`` on every interface, with TLS when ``certfile`` and ``keyfile``
    are given."""

    port: int
    certfile: Path | None = None
    keyfile: Path | None = None


@dataclass(frozen=True)
class WardBrokerFiles:
    """What one run wrote, and which users it added, kept (with their passwords) and removed."""

    password_file: Path
    acl_file: Path
    config_file: Path
    secrets_folder: Path
    added: tuple[str, ...]
    kept: tuple[str, ...]
    removed: tuple[str, ...]


def write_ward_broker(folder: Path, beds: Sequence[str], stations: Sequence[str], *,
                      topic_prefix: str = "appliance", listener: Listener | None = None,
                      persistence_location: Path | None = None, broker_user: str | None = None) -> WardBrokerFiles:
    """Write the ward broker's files into ``folder`` (made if missing) for ``beds`` and ``stations``; every input
    is checked before anything is written. ``persistence_location`` is left out by default: Debian's
    mosquitto.conf sets it, and a second one stops Mosquitto."""
    check_names(beds, stations)
    check_topic_prefix(topic_prefix)
    if listener is not None:
        listener = _checked_listener(listener)
    owner = None if broker_user is None else _account(broker_user)
    folder = Path(folder).absolute()
    if folder.exists() and not folder.is_dir():
        raise ConfigError(f"--out {folder} is a file, not a folder")
    if not folder.parent.is_dir():
        raise ConfigError(f"--out {folder}: the folder {folder.parent} does not exist")
    password_file, secrets_folder = folder / "passwords", folder / "secrets"
    hashes = read_password_file(password_file)
    folder.mkdir(mode=0o755, exist_ok=True)
    secrets_folder.mkdir(mode=0o700, exist_ok=True)
    secrets_folder.chmod(0o700)

    users = [*beds, *stations]
    added, kept = [], []
    for user in users:
        secret = secrets_folder / f"{user}.password"
        if user in hashes:
            kept.append(user)
        elif secret.exists():           # handed out, but its line was lost: the bed still has this password
            hashes[user] = password_hash(read_secret(secret, "delete it to give that user a new password"))
            kept.append(user)
        else:
            password = secrets.token_urlsafe(PASSWORD_BYTES)
            write_atomic(secret, password + "\n")
            hashes[user] = password_hash(password)
            added.append(user)
    secret_files = {path.name.removesuffix(".password"): path for path in secrets_folder.glob("*.password")}
    removed = sorted({*hashes, *secret_files} - set(users))
    for user in removed:
        if user in secret_files:
            secret_files[user].unlink()

    acl_file, config_file = folder / "acl", folder / "ward-broker.conf"
    _write_for_broker(password_file, "".join(f"{user}:{hashes[user]}\n" for user in users), owner)
    _write_for_broker(acl_file, acl_text(stations, topic_prefix), owner)
    write_atomic(config_file, config_text(password_file, acl_file, topic_prefix, listener, persistence_location))
    config_file.chmod(0o644)                # read as root at start, and as the broker's user on reload
    return WardBrokerFiles(password_file, acl_file, config_file, secrets_folder, tuple(added), tuple(kept),
                           tuple(removed))


def password_hash(password: str) -> str:
    """``password`` as a Mosquitto 2 password file holds it: PBKDF2-SHA512 with a random salt."""
    salt = secrets.token_bytes(SALT_BYTES)
    digest = hashlib.pbkdf2_hmac("sha512", password.encode("utf-8"), salt, PBKDF2_ITERATIONS)
    return f"$7${PBKDF2_ITERATIONS}${base64.b64encode(salt).decode()}${base64.b64encode(digest).decode()}"


def acl_text(stations: Sequence[str], topic_prefix: str) -> str:
    """The ACL: ``pattern`` lines for every bed, and one section per station.

    Mosquitto applies ``pattern`` lines to every user, stations too, so a station could write
    ``<prefix>/<station>/summary`` as a bed of that name; its own ``deny`` closes that, and Mosquitto checks a
    user's denials before any grant."""
    lines = ["# Written by `appliance ward-broker`, whole on every run: edit its beds and stations, not this file.",
             "# A bed's user name is its bed id: it writes its own topics and reads its own confirmations and "
             "commands.",
             *(f"pattern write {topic_prefix}/%u/{kind}" for kind in BED_TOPICS),
             *(f"pattern read {topic_prefix}/%u/{kind}" for kind in STATION_TOPICS)]
    for station in stations:
        lines += ["", "# A ward station: every bed's topics, and the confirmations and commands it sends them.",
                  f"user {station}", f"topic deny {topic_prefix}/{station}/#",
                  *(f"topic read {topic_prefix}/+/{kind}" for kind in BED_TOPICS),
                  *(f"topic write {topic_prefix}/+/{kind}" for kind in STATION_TOPICS)]
    return "\n".join(lines) + "\n"


def config_text(password_file: Path, acl_file: Path, topic_prefix: str, listener: Listener | None = None,
                persistence_location: Path | None = None) -> str:
    """The lines for ``/etc/mosquitto/conf.d``; the listener, its TLS files and the persistence folder only when
    given."""
    lines = [f"# The ward's broker for beds under {topic_prefix}/, written by `appliance ward-broker`.",
             "# Logins only, and each bed and station held to its own topics by the ACL; after a new run of",
             "# appliance ward-broker, `systemctl reload mosquitto` (SIGHUP) reads both files again.",
             "allow_anonymous false", f"password_file {password_file}", f"acl_file {acl_file}",
             "# The station's session and the alarms queued for it survive a restart of the broker.",
             "persistence true"]
    if persistence_location is None:
        lines.append("# persistence_location: Debian's /etc/mosquitto/mosquitto.conf sets it; a second stops Mosquitto")
    else:
        lines.append(f"persistence_location {str(Path(persistence_location).absolute()).rstrip('/')}/")
    if listener is not None:
        lines.append(f"listener {listener.port}")
        if listener.certfile is not None:
            lines += [f"certfile {listener.certfile}", f"keyfile {listener.keyfile}"]
    return "\n".join(lines) + "\n"


def check_name(name: str, what: str) -> str:
    """``name`` if it can be a user name in the password file and a level of a topic, else a ConfigError naming
    it and ``what`` it is ("bed id", "station")."""
    if not 1 <= len(name) <= MAX_NAME \
            or any(c in FORBIDDEN_IN_NAMES or c.isspace() or unicodedata.category(c) == "Cc" for c in name):
        raise ConfigError(f"{what} {name!r}: must be 1-{MAX_NAME} characters without '/', '+', '#', ':', spaces "
                          f"or control characters (NUL, tab, newline)")
    return name


def check_names(beds: Sequence[str], stations: Sequence[str]) -> None:
    """Every bed id and station user name valid and given once, and no station named as a bed: the beds'
    ``pattern`` lines would let it write that bed's topics."""
    if not beds:
        raise ConfigError("no beds: give each bed's id with --bed or --beds-file")
    if not stations:
        raise ConfigError("no station: give the ward station's user name with --station")
    for names, what in ((beds, "bed id"), (stations, "station")):
        seen = set()
        for name in names:
            check_name(name, what)
            if name in seen:
                raise ConfigError(f"{what} {name!r} is given twice")
            seen.add(name)
    for station in stations:
        if station in beds:
            raise ConfigError(f"station {station!r} is also a bed id: it could publish that bed's summary")


def check_topic_prefix(prefix: str) -> str:
    """``prefix`` if it is a topic without wildcards, empty levels, spaces or '%' (the ACL's substitutions)."""
    levels = prefix.split("/")
    if not prefix or len(prefix) > 200 or any(not level for level in levels) or prefix.startswith("$") \
            or any(c in "+#%" or c.isspace() or unicodedata.category(c) == "Cc" for c in prefix):
        raise ConfigError(f"--topic-prefix {prefix!r}: must be a topic such as 'appliance' or 'hospital/ward3', "
                          f"without '+', '#', '%', spaces, empty levels or a leading '$'")
    return prefix


def beds_from_file(path: Path) -> list[str]:
    """The bed ids in ``path``, one a line; blank lines and lines starting with '#' are skipped."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"--beds-file {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"--beds-file {path}: cannot read it ({exc})") from None
    beds = []
    for number, line in enumerate(text.splitlines(), start=1):
        bed = line.strip()
        if not bed or bed.startswith("#"):
            continue
        try:
            beds.append(check_name(bed, "bed id"))
        except ConfigError as exc:
            raise ConfigError(f"--beds-file {path} line {number}: {exc}") from None
    return beds


def read_password_file(path: Path) -> dict[str, str]:
    """The users and hashes of an existing password file, in its order; {} when there is none."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return {}
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read the broker's password file ({exc})") from None
    hashes = {}
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        user, colon, hashed = line.partition(":")
        if not (colon and user and hashed):
            raise ConfigError(f"{path} line {number}: not user:hash; move the file away to start afresh")
        hashes[user] = hashed
    return hashes


def _checked_listener(listener: Listener) -> Listener:
    if not 1 <= listener.port <= 65535:
        raise ConfigError(f"--listener takes a port from 1 to 65535, got {listener.port}")
    if (listener.certfile is None) != (listener.keyfile is None):
        raise ConfigError("--certfile and --keyfile go together: TLS needs the certificate and its key")
    for option, path in (("--certfile", listener.certfile), ("--keyfile", listener.keyfile)):
        if path is not None and not Path(path).is_file():
            raise ConfigError(f"{option} {path}: no such file")
    if listener.certfile is None or listener.keyfile is None:
        return listener
    return Listener(listener.port, Path(listener.certfile).absolute(), Path(listener.keyfile).absolute())


def _account(user: str) -> tuple[int, int]:
    try:
        account = pwd.getpwnam(user)
    except KeyError:
        raise ConfigError(f"--broker-user {user!r}: no such user on this machine") from None
    if os.geteuid() not in (0, account.pw_uid):
        raise ConfigError(f"--broker-user {user!r}: only root can give files to another user")
    return account.pw_uid, account.pw_gid


def _write_for_broker(path: Path, text: str, owner: tuple[int, int] | None) -> None:
    """``text`` in ``path``, 0600 and owned by ``owner`` (uid, gid), or by whoever owned the file it replaces."""
    if owner is None and path.exists():
        status = path.stat()
        owner = status.st_uid, status.st_gid
    write_atomic(path, text)
    if owner is not None:
        try:
            os.chown(path, *owner)
        except PermissionError:
            raise ConfigError(f"{path}: cannot give it back to uid {owner[0]}, who owned it: run as root") from None
