"""runs, run events, models

Revision ID: 0001
Revises:
Create Date: 2026-11-21 10:33:33.186139

The first schema of the registry (see registry/models.py). Times are naive UTC DateTime text;
registry.models.UTCDateTime adds and strips the UTC zone. It deliberately does not import the models:
a migration is a frozen snapshot of the schema at its revision.
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0001'
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table('runs',
    sa.Column('id', sa.String(length=64), nullable=False),
    sa.Column('component', sa.String(length=32), nullable=False),
    sa.Column('config', sa.JSON(), nullable=False),
    sa.Column('dataset_fingerprint', sa.String(length=128), nullable=True),
    sa.Column('queue', sa.String(length=64), server_default='pi', nullable=False),
    sa.Column('priority', sa.Integer(), server_default='0', nullable=False),
    sa.Column('sequence_id', sa.String(length=64), nullable=True),
    sa.Column('sequence_index', sa.Integer(), nullable=True),
    sa.Column('state', sa.String(length=16), nullable=False),
    sa.Column('pause_reason', sa.String(length=16), nullable=True),
    sa.Column('desired_state', sa.String(length=16), server_default='run', nullable=False),
    sa.Column('requested_reason', sa.String(length=16), nullable=True),
    sa.Column('throttle_level', sa.Integer(), server_default='0', nullable=False),
    sa.Column('step', sa.Integer(), server_default='0', nullable=False),
    sa.Column('total_steps', sa.Integer(), nullable=False),
    sa.Column('last_checkpoint', sa.Text(), nullable=True),
    sa.Column('error_message', sa.Text(), nullable=True),
    sa.Column('attempt', sa.Integer(), server_default='1', nullable=False),
    sa.Column('max_attempts', sa.Integer(), server_default='3', nullable=False),
    sa.Column('celery_task_id', sa.String(length=64), nullable=True),
    sa.Column('worker_host', sa.String(length=255), nullable=True),
    sa.Column('worker_pid', sa.Integer(), nullable=True),
    sa.Column('run_dir', sa.Text(), nullable=False),
    sa.Column('created_at', sa.DateTime(), nullable=False),
    sa.Column('queued_at', sa.DateTime(), nullable=True),
    sa.Column('started_at', sa.DateTime(), nullable=True),
    sa.Column('finished_at', sa.DateTime(), nullable=True),
    sa.Column('updated_at', sa.DateTime(), nullable=False),
    sa.Column('heartbeat_at', sa.DateTime(), nullable=True),
    sa.Column('loss', sa.Float(), nullable=True),
    sa.Column('steps_per_s', sa.Float(), nullable=True),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_runs'))
    )
    with op.batch_alter_table('runs', schema=None) as batch_op:
        batch_op.create_index('ix_runs_dispatch', ['state', 'queue', 'priority', 'created_at'], unique=False)
        batch_op.create_index(batch_op.f('ix_runs_sequence_id'), ['sequence_id'], unique=False)

    op.create_table('models',
    sa.Column('id', sa.Integer(), autoincrement=True, nullable=False),
    sa.Column('component', sa.String(length=32), nullable=False),
    sa.Column('checkpoint_path', sa.Text(), nullable=False),
    sa.Column('run_id', sa.String(length=64), nullable=True),
    sa.Column('metrics', sa.JSON(none_as_null=True), nullable=True),
    sa.Column('gate_result', sa.JSON(none_as_null=True), nullable=True),
    sa.Column('promoted_at', sa.DateTime(), nullable=True),
    sa.Column('created_at', sa.DateTime(), nullable=False),
    sa.ForeignKeyConstraint(['run_id'], ['runs.id'], name=op.f('fk_models_run_id_runs'), ondelete='SET NULL'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_models'))
    )
    with op.batch_alter_table('models', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_models_run_id'), ['run_id'], unique=False)
        batch_op.create_index('uq_models_promoted_component', ['component'], unique=True, sqlite_where=sa.text('promoted_at IS NOT NULL'))

    op.create_table('run_events',
    sa.Column('id', sa.Integer(), autoincrement=True, nullable=False),
    sa.Column('run_id', sa.String(length=64), nullable=False),
    sa.Column('time', sa.DateTime(), nullable=False),
    sa.Column('kind', sa.String(length=16), nullable=False),
    sa.Column('payload', sa.JSON(), nullable=False),
    sa.ForeignKeyConstraint(['run_id'], ['runs.id'], name=op.f('fk_run_events_run_id_runs'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_run_events'))
    )
    with op.batch_alter_table('run_events', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_run_events_run_id'), ['run_id'], unique=False)



def downgrade() -> None:
    with op.batch_alter_table('run_events', schema=None) as batch_op:
        batch_op.drop_index(batch_op.f('ix_run_events_run_id'))

    op.drop_table('run_events')
    with op.batch_alter_table('models', schema=None) as batch_op:
        batch_op.drop_index('uq_models_promoted_component', sqlite_where=sa.text('promoted_at IS NOT NULL'))
        batch_op.drop_index(batch_op.f('ix_models_run_id'))

    op.drop_table('models')
    with op.batch_alter_table('runs', schema=None) as batch_op:
        batch_op.drop_index(batch_op.f('ix_runs_sequence_id'))
        batch_op.drop_index('ix_runs_dispatch')

    op.drop_table('runs')
