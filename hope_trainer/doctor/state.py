"""The doctor's checks of this deployment's state: $HOPE_HOME, the token file, the registry's
migration level, the broker, the systemd services. Each one reads and never writes: the database
is opened read-only (and immutable when no WAL is in use, so not even a -shm file appears), the
token is never made, nothing is chmod-ed, migrated or created."""
from __future__ import annotations

import os
import shutil
import sqlite3
import stat
import subprocess
from pathlib import Path
from typing import Any

import migrations
from hope_trainer.doctor.check import FAIL, OK, SKIP, WARN, Check
from registry.broker import broker_path

SERVICES = ("hope-daemon", "hope-webapp", "hope-worker")
REDIS_TIMEOUT_S = 2.0
SYSTEMCTL_TIMEOUT_S = 10.0
FIRST_START = "the first start of serve (or the daemon) makes it"


def check_home(settings: Any) -> Check:
    home = Path(settings.home)
    try:
        st = home.stat()
    except FileNotFoundError:
        return Check("home", WARN, f"{home} does not exist yet", FIRST_START)
    mode = stat.S_IMODE(st.st_mode)
    detail = f"{home} mode {mode:04o}"
    if st.st_uid != os.geteuid():
        return Check("home", FAIL, f"{detail}, owned by uid {st.st_uid}, not by this user ({os.geteuid()})",
                     f"run as its owner, or sudo chown -R $USER {home}")
    if not os.access(home, os.W_OK | os.X_OK):
        return Check("home", FAIL, f"{detail}: not writable by this user", f"chmod 700 {home}")
    if mode & 0o077:
        return Check("home", WARN, f"{detail}: other local users can look inside (the next start tightens it)",
                     f"chmod 700 {home}")
    return Check("home", OK, detail)


def check_token(settings: Any) -> Check:
    from webapp.auth import MIN_TOKEN_CHARS, token_path  # lazy: loads flask

    path = token_path(settings)
    try:
        st = path.stat()
    except FileNotFoundError:
        return Check("token", WARN, f"{path} does not exist yet", f"{FIRST_START} (serve prints it)")
    mode = stat.S_IMODE(st.st_mode)
    detail = f"{path} mode {mode:04o}"
    if st.st_uid != os.geteuid():
        return Check("token", FAIL, f"{detail}, owned by uid {st.st_uid}, not by this user",
                     f"sudo chown $USER {path} && chmod 600 {path}")
    if mode & 0o077:
        return Check("token", FAIL, f"{detail}: readable by other local users, and the webapp refuses it",
                     f"chmod 600 {path}")
    try:
        length = len(path.read_text(encoding="utf-8").strip())
    except (OSError, UnicodeDecodeError) as exc:
        return Check("token", FAIL, f"{detail}: cannot be read ({exc})", f"delete {path}; {FIRST_START}")
    if length < MIN_TOKEN_CHARS:
        return Check("token", FAIL, f"{detail}: the token is shorter than {MIN_TOKEN_CHARS} characters",
                     f"delete {path}; {FIRST_START}")
    return Check("token", OK, detail)


def _heads() -> tuple[set[str], set[str]]:
    """(the heads, every revision) of the migrations this code carries."""
    from alembic.script import ScriptDirectory  # lazy: loads alembic


    scripts = ScriptDirectory(str(Path(migrations.__file__).resolve().parent))
    return set(scripts.get_heads()), {s.revision for s in scripts.walk_revisions()}


def _stored_revisions(path: Path) -> set[str] | None:
    """The alembic_version rows, read without writing anything; None when there is no such table."""
    wal = path.with_name(path.name + "-wal").exists()
    # mode=ro alone may create -wal/-shm files next to a WAL database; with no WAL in use the file
    # is all there is, and immutable=1 opens it without locks or side files.
    uri = f"file:{path}?mode=ro" if wal else f"file:{path}?immutable=1"
    con = sqlite3.connect(uri, uri=True, timeout=5)
    try:
        if not con.execute("SELECT 1 FROM sqlite_master WHERE type='table' AND name='alembic_version'").fetchone():
            return None
        return {row[0] for row in con.execute("SELECT version_num FROM alembic_version")}
    finally:
        con.close()


def check_database(settings: Any) -> Check:
    from registry.db import db_path  # lazy: loads sqlalchemy

    path = db_path(settings)
    if not path.exists():
        return Check("database", WARN, f"{path} does not exist yet", f"{FIRST_START} and migrates it")
    try:
        stored = _stored_revisions(path)
    except sqlite3.Error as exc:
        return Check("database", FAIL, f"{path} cannot be read: {exc}",
                     "restore hope.db from its backup (docs/pi.md, 'Upgrade')")
    heads, known = _heads()
    want = ", ".join(sorted(heads))
    if not stored:
        return Check("database", FAIL, f"{path} has no migration level (not a registry, or never migrated)",
                     "start the daemon once (it migrates), or move the file away")
    have = ", ".join(sorted(stored))
    if stored == heads:
        return Check("database", OK, f"{path} at {have} (head)")
    if stored - known:
        return Check("database", FAIL, f"{path} at {have}, newer than this code (head {want})",
                     "install the newer hope-trainer this database was made with, or restore a backup")
    return Check("database", WARN, f"{path} at {have}, behind head {want}: the next daemon start migrates it",
                 "back up hope.db first (docs/pi.md, 'Upgrade'), then restart the daemon")


def _writable_where(path: Path) -> tuple[bool, Path]:
    """Whether `path` (or, if not made yet, the nearest existing dir above it) is writable."""
    probe = path
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if probe == path:
        return os.access(path, os.W_OK) and os.access(path.parent, os.W_OK | os.X_OK), path
    return os.access(probe, os.W_OK | os.X_OK), probe


def check_broker(settings: Any) -> Check:
    url = getattr(settings, "redis_url", None)
    if not url:
        path = broker_path(settings)
        ok, where = _writable_where(path)
        made = "" if where == path else " (made on first use)"
        if not ok:
            return Check("broker", FAIL, f"embedded broker {path}: {where} is not writable",
                         f"chown/chmod {where} so this user can write it")
        return Check("broker", OK, f"embedded broker {path} writable{made}")
    return _redis_ping(url)


def _redis_ping(url: str) -> Check:
    shown = _without_password(url)
    try:
        import redis  # lazy: loads redis
    except ImportError:
        return Check("broker", FAIL, f"redis_url is {shown} but the redis package is not installed", "sudo make install")
    try:
        client = redis.Redis.from_url(url, socket_connect_timeout=REDIS_TIMEOUT_S, socket_timeout=REDIS_TIMEOUT_S)
        try:
            client.ping()
        finally:
            client.close()
    except (redis.RedisError, OSError, ValueError) as exc:
        return Check("broker", FAIL, f"Redis at {shown} does not answer PING: {exc}",
                     "sudo systemctl start redis-server, or remove redis_url to use the embedded broker")
    return Check("broker", OK, f"Redis at {shown} answers PING")


def _without_password(url: str) -> str:
    scheme, sep, rest = url.partition("://")
    if "@" in rest:
        rest = "***@" + rest.rsplit("@", 1)[1]
    return scheme + sep + rest


def has_systemd() -> bool:
    """systemd runs this machine (not merely installed: a container has systemctl but no manager)."""
    return shutil.which("systemctl") is not None and Path("/run/systemd/system").is_dir()


def check_services(_settings: Any) -> list[Check]:
    if not has_systemd():
        return [Check("services", SKIP, "systemd is not running here; the services are not checked")]
    return [_service(unit) for unit in SERVICES]


def _service(unit: str) -> Check:
    try:
        out = subprocess.run(["systemctl", "show", "--property=LoadState,ActiveState,SubState", f"{unit}.service"],
                             capture_output=True, text=True, timeout=SYSTEMCTL_TIMEOUT_S, check=False).stdout
    except (OSError, subprocess.SubprocessError) as exc:
        return Check(unit, WARN, f"systemctl show failed: {exc}", f"systemctl status {unit}")
    props = dict(line.split("=", 1) for line in out.splitlines() if "=" in line)
    load, active, sub = props.get("LoadState", "?"), props.get("ActiveState", "?"), props.get("SubState", "?")
    if load == "not-found":
        return Check(unit, SKIP, "not installed", "sudo ./systemd/install.sh installs the units (or run serve)")
    detail = f"{active} ({sub})"
    if active == "active":
        return Check(unit, OK, detail)
    if active == "failed":
        return Check(unit, FAIL, detail, f"journalctl -u {unit} -b -p warning; then sudo systemctl restart {unit}")
    return Check(unit, WARN, detail, f"sudo systemctl enable --now {unit}")
