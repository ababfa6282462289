"""The registry database: one SQLite file (WAL) under $HOPE_HOME, migrated by Alembic.

SQLite is the source of truth for every run, so several processes (daemon, worker child, CLI,
webapp) write to it at once. Three choices keep that safe:
- WAL, so readers never block the one writer, and a 30 s busy timeout, so a writer waits
  for the lock instead of failing;
- every read-write session opens with BEGIN IMMEDIATE: a deferred transaction that reads and
  then writes can fail at once with SQLITE_BUSY (its snapshot went stale) without waiting on
  the busy timeout, and it would also allow lost updates in read-modify-write state changes;
- an fcntl lock around migrations, so two processes starting together do not race Alembic.

Engines are not fork-safe: a forked child (the Celery worker child) opens its own Registry.
"""
from __future__ import annotations

import fcntl
import sqlite3
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from sqlalchemy import create_engine, event, inspect
from sqlalchemy.engine import Engine
from sqlalchemy.orm import Session, sessionmaker

import migrations
from hope_models.durable import fsync_path

if TYPE_CHECKING:
    from hope_models.settings import Settings

DB_FILENAME = "hope.db"
BUSY_TIMEOUT_MS = 30_000
# Session option read by the "begin" listener: how a transaction starts.
_BEGIN_OPTION = "hope_sqlite_begin"


class RegistryError(RuntimeError):
    """The registry database cannot be used as it is (not migrated, wrong path); the message names the file."""


def db_path(settings: Settings) -> Path:
    return Path(settings.home) / DB_FILENAME


def _on_connect(dbapi_connection: sqlite3.Connection, _record) -> None:
    # Take transaction control away from the sqlite3 module (it would issue its own deferred
    # BEGIN before DML); the "begin" listener below issues BEGIN [IMMEDIATE] instead.
    dbapi_connection.isolation_level = None
    cursor = dbapi_connection.cursor()
    try:
        cursor.execute("PRAGMA journal_mode=WAL")
        cursor.execute(f"PRAGMA busy_timeout={BUSY_TIMEOUT_MS}")
        cursor.execute("PRAGMA foreign_keys=ON")
        # NORMAL is durable across process crashes in WAL mode (only a power loss can drop
        # the last commits), and much cheaper than FULL on an SD card.
        cursor.execute("PRAGMA synchronous=NORMAL")
    finally:
        cursor.close()


def _on_begin(conn) -> None:
    conn.exec_driver_sql(conn.get_execution_options().get(_BEGIN_OPTION, "BEGIN IMMEDIATE"))


def make_engine(path: Path | str) -> Engine:
    path = Path(path)
    engine = create_engine(f"sqlite:///{path}", connect_args={"timeout": BUSY_TIMEOUT_MS / 1000})
    event.listen(engine, "connect", _on_connect)
    event.listen(engine, "begin", _on_begin)
    return engine


def _engine_path(engine: Engine) -> Path:
    database = engine.url.database
    if not database or database == ":memory:":
        raise RegistryError(f"the registry needs a database file, not {engine.url}")
    return Path(database)


def _alembic_config(connection):
    from alembic.config import Config  # lazy: loads alembic


    cfg = Config()
    cfg.set_main_option("script_location", str(Path(migrations.__file__).resolve().parent))
    cfg.attributes["connection"] = connection
    return cfg


@contextmanager
def _migrate_lock(db_file: Path) -> Iterator[None]:
    db_file.parent.mkdir(parents=True, exist_ok=True)
    lock_file = db_file.with_name(db_file.name + ".migrate.lock")
    with open(lock_file, "a+") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


def _run_alembic(engine_or_path: Engine | Path | str, action: str, revision: str) -> None:
    from alembic import command  # lazy: loads alembic

    own = not isinstance(engine_or_path, Engine)
    engine = engine_or_path if isinstance(engine_or_path, Engine) else make_engine(engine_or_path)
    try:
        with _migrate_lock(_engine_path(engine)):
            if action == "upgrade":
                backup_before_upgrade(engine, revision)
            # One transaction for the whole migration: SQLite has transactional DDL, so a crash
            # mid-migration leaves the previous revision intact.
            with engine.begin() as connection:
                getattr(command, action)(_alembic_config(connection), revision)
    finally:
        if own:
            engine.dispose()


def backup_before_upgrade(engine: Engine, revision: str = "head") -> Path | None:
    """Copy an existing registry that `revision` would change to `hope.db.before-<to>-from-<from>`
    (SQLite's online backup: consistent even with a reader open) before it is migrated, so an
    upgrade that goes wrong can be undone by hand. Nothing for a new registry or one already there."""
    from alembic.script import ScriptDirectory  # lazy: loads alembic

    current = current_revision(engine)
    if current is None:
        return None
    with engine.connect() as connection:
        script = ScriptDirectory.from_config(_alembic_config(connection))
    target = script.get_current_head() if revision == "head" else script.get_revision(revision).revision
    if target == current:
        return None
    db_file = _engine_path(engine)
    dest = db_file.with_name(f"{db_file.name}.before-{target}-from-{current}")
    tmp = dest.with_name(dest.name + ".tmp")
    tmp.unlink(missing_ok=True)
    src, dst = sqlite3.connect(db_file), sqlite3.connect(tmp)
    try:
        src.backup(dst)
    finally:
        dst.close()
        src.close()
    fsync_path(tmp)
    tmp.replace(dest)
    fsync_path(dest.parent)
    return dest


def migrate(engine_or_path: Engine | Path | str, revision: str = "head") -> None:
    """Upgrade the database to `revision` (idempotent; cheap when already there)."""
    _run_alembic(engine_or_path, "upgrade", revision)


def downgrade(engine_or_path: Engine | Path | str, revision: str = "base") -> None:
    _run_alembic(engine_or_path, "downgrade", revision)


def current_revision(engine: Engine) -> str | None:
    from alembic.runtime.migration import MigrationContext  # lazy: loads alembic

    with engine.connect() as connection:
        return MigrationContext.configure(connection).get_current_revision()


class Registry:
    """The open registry: an engine plus sessions that commit on success and roll back on error."""

    def __init__(self, engine: Engine, path: Path):
        self.engine = engine
        self.path = path
        self._sessions = sessionmaker(bind=engine, expire_on_commit=False)
        self._readonly_engine = engine.execution_options(**{_BEGIN_OPTION: "BEGIN"})
        self._readonly_sessions = sessionmaker(bind=self._readonly_engine, expire_on_commit=False)

    @classmethod
    def open(cls, settings: Settings, *, migrate: bool = True) -> "Registry":
        home = Path(settings.home)
        home.mkdir(parents=True, exist_ok=True)
        path = db_path(settings)
        engine = make_engine(path)
        try:
            if migrate:
                _run_alembic(engine, "upgrade", "head")
            elif not inspect(engine).has_table("runs"):
                raise RegistryError(
                    f"{path}: the registry is not set up (no runs table); start the daemon or run any "
                    "run_trainer.py daemon command once to migrate it"
                )
        except BaseException:
            engine.dispose()
            raise
        return cls(engine, path)

    @contextmanager
    def session(self, *, readonly: bool = False) -> Iterator[Session]:
        """A Session in one transaction: committed when the block ends, rolled back on error.

        Read-write sessions (the default) start with BEGIN IMMEDIATE: they take the write lock
        up front (waiting up to the busy timeout), so read-then-update code is serialised.
        readonly=True starts a deferred transaction (a consistent snapshot; never blocks writers);
        writing in it may fail with "database is locked" under contention, so do not.
        """
        factory = self._readonly_sessions if readonly else self._sessions
        with factory() as session:
            try:
                yield session
                session.commit()
            except BaseException:
                session.rollback()
                raise

    def close(self) -> None:
        self.engine.dispose()

    def __enter__(self) -> "Registry":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
