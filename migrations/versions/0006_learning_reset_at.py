"""learning reset time

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-27 12:00:00.000000

learning_state.reset_at: when the app last reset learning (POST /api/learning/reset,
registry/learning.reset): the watermark was forgotten then, and the app's surprise history starts
after it. One nullable column: existing rows keep every value and read as never reset; the
downgrade drops it. Times are naive UTC DateTime text, as in 0001.
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0006'
down_revision = '0005'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('learning_state', schema=None) as batch_op:
        batch_op.add_column(sa.Column('reset_at', sa.DateTime(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table('learning_state', schema=None) as batch_op:
        batch_op.drop_column('reset_at')
