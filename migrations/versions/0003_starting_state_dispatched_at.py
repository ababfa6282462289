"""the starting state: runs.dispatched_at

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-23 16:20:00.000000

A run whose task was sent but that no worker child has claimed is now `starting`, not `running`
(registry/runs.py): nothing trains it, and with no worker on its queue it would otherwise show
`running` for ever. runs.dispatched_at says since when it waits (a re-send keeps it).

Rows written before this revision that are in that situation (running, no worker pid) become
starting, with dispatched_at from heartbeat_at (the time their task was last sent), so claim(),
cancel and the re-send treat them by the new rules; downgrading turns starting back into running
(the old rules' "dispatched, unclaimed"). The state column is a plain string: no constraint moves.
Not batch mode: copying `runs` means DROP TABLE runs, which with foreign keys on deletes every
run_events row (ON DELETE CASCADE); SQLite adds and (>= 3.35) drops a nullable column in place.
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0003'
down_revision = '0002'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column('runs', sa.Column('dispatched_at', sa.DateTime(), nullable=True))
    op.execute("UPDATE runs SET state = 'starting', dispatched_at = heartbeat_at "
               "WHERE state = 'running' AND worker_pid IS NULL")


def downgrade() -> None:
    op.execute("UPDATE runs SET state = 'running' WHERE state = 'starting'")
    op.execute('ALTER TABLE runs DROP COLUMN dispatched_at')
