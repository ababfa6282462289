"""Alembic environment for the registry, run programmatically by registry.db.migrate.

There is no alembic.ini: registry.db builds the Config and passes an open connection (inside one
transaction, under the migrate lock) as config.attributes["connection"]. For autogenerating a new
revision by hand, see migrations/README.md.
"""
from __future__ import annotations

from alembic import context
from sqlalchemy import Connection

from registry.db import make_engine
from registry.models import Base

target_metadata = Base.metadata


def _configure(connection: Connection) -> None:
    context.configure(
        connection=connection,
        target_metadata=target_metadata,
        # SQLite cannot ALTER most things; batch mode copies the table instead.
        render_as_batch=True,
        compare_type=True,
    )


def run_migrations_online() -> None:
    connection = context.config.attributes.get("connection")
    if connection is not None:
        _configure(connection)
        with context.begin_transaction():
            context.run_migrations()
        return
    url = context.config.get_main_option("sqlalchemy.url")
    if not url:
        raise RuntimeError("migrations/env.py: pass a connection (registry.db.migrate) or set sqlalchemy.url")

    engine = make_engine(url.removeprefix("sqlite:///"))
    try:
        with engine.begin() as conn:
            _configure(conn)
            with context.begin_transaction():
                context.run_migrations()
    finally:
        engine.dispose()


if context.is_offline_mode():
    raise RuntimeError("migrations/env.py: offline (--sql) mode is not supported; migrate a database file")
run_migrations_online()
