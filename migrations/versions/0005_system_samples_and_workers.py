"""system samples and workers

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-26 20:40:00.000000

system_samples: the daemon's host history (memory, temperature, CPU, throttle level every
system_sample_s, the last 24 h kept), so the System page's chart survives a restart and the
standalone webapp can read it. workers: the Celery workers that beat (name, host, pid, queues,
report mode, start, last beat, stop, current run). New tables only: no existing row changes and
nothing is copied; the downgrade drops them. Times are naive UTC DateTime text, as in 0001.
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0005'
down_revision = '0004'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        'system_samples',
        sa.Column('id', sa.Integer(), autoincrement=True, nullable=False),
        sa.Column('time', sa.DateTime(), nullable=False),
        sa.Column('mem_percent', sa.Float(), nullable=True),
        sa.Column('mem_used_mb', sa.Float(), nullable=True),
        sa.Column('mem_available_mb', sa.Float(), nullable=True),
        sa.Column('mem_total_mb', sa.Float(), nullable=True),
        sa.Column('temp_c', sa.Float(), nullable=True),
        sa.Column('cpu_percent', sa.Float(), nullable=True),
        sa.Column('throttle_level', sa.Integer(), nullable=True),
        sa.PrimaryKeyConstraint('id', name=op.f('pk_system_samples')),
    )
    with op.batch_alter_table('system_samples', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_system_samples_time'), ['time'], unique=False)
    op.create_table(
        'workers',
        sa.Column('name', sa.String(length=255), nullable=False),
        sa.Column('host', sa.String(length=255), nullable=False),
        sa.Column('pid', sa.Integer(), nullable=False),
        sa.Column('queues', sa.JSON(), nullable=False),
        sa.Column('report', sa.String(length=8), nullable=False),
        sa.Column('heartbeat_s', sa.Float(), nullable=False),
        sa.Column('started_at', sa.DateTime(), nullable=False),
        sa.Column('last_seen', sa.DateTime(), nullable=False),
        sa.Column('stopped_at', sa.DateTime(), nullable=True),
        sa.Column('current_run_id', sa.String(length=64), nullable=True),
        sa.PrimaryKeyConstraint('name', name=op.f('pk_workers')),
    )


def downgrade() -> None:
    op.drop_table('workers')
    with op.batch_alter_table('system_samples', schema=None) as batch_op:
        batch_op.drop_index(batch_op.f('ix_system_samples_time'))
    op.drop_table('system_samples')
