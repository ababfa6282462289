"""continuous learning state

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-23 22:32:19.873001

learning_state: the one row continuous learning keeps in the registry, so that the daemon and the
webapp (two processes in production) share it and it survives restarts: whether the app paused
learning (and which runs that pause paused), the daemon's last decision (phase), and the last auto
run with the inbox episodes it was queued for (the watermark). A new table, so no existing row
changes and nothing is copied; the downgrade drops it. Times are naive UTC DateTime text, as in 0001.
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0004'
down_revision = '0003'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        'learning_state',
        sa.Column('id', sa.Integer(), nullable=False),
        sa.Column('paused', sa.Boolean(), server_default='0', nullable=False),
        sa.Column('paused_at', sa.DateTime(), nullable=True),
        sa.Column('paused_runs', sa.JSON(none_as_null=True), nullable=True),
        sa.Column('local_queues', sa.JSON(none_as_null=True), nullable=True),
        sa.Column('phase', sa.String(length=32), server_default='idle', nullable=False),
        sa.Column('phase_detail', sa.Text(), nullable=True),
        sa.Column('phase_at', sa.DateTime(), nullable=True),
        sa.Column('decision', sa.JSON(none_as_null=True), nullable=True),
        sa.Column('watermark', sa.JSON(none_as_null=True), nullable=True),
        sa.Column('last_auto_sequence_id', sa.String(length=64), nullable=True),
        sa.Column('last_auto_at', sa.DateTime(), nullable=True),
        sa.Column('last_auto_reason', sa.Text(), nullable=True),
        sa.Column('updated_at', sa.DateTime(), nullable=False),
        sa.PrimaryKeyConstraint('id', name=op.f('pk_learning_state')),
    )


def downgrade() -> None:
    op.drop_table('learning_state')
