"""promotion history and loop closure

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-21 11:17:16.878880

models: version ("<run>@<step>:<sha12>"), demoted_at, previous_model_id (what was served before
this one was promoted: a rollback goes back to it); runs: first_inference_at and loop_closure_s
(run finished -> first inference on its weights). Every new column is nullable, so rows written
at 0001 stay valid (their version is unknown: null).

SQLite cannot add a foreign key in place, so batch mode copies `models` (nothing else references
it, so the copy's DROP TABLE touches no other table's rows); the partial unique index
(one promoted model per component) is re-created explicitly after the copy, because reflection
does not carry its WHERE clause over. Times are naive UTC DateTime text, as in 0001.
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0002'
down_revision = '0001'
branch_labels = None
depends_on = None

_PROMOTED_INDEX = 'uq_models_promoted_component'
_PROMOTED_WHERE = sa.text('promoted_at IS NOT NULL')


def _recreate_promoted_index() -> None:
    with op.batch_alter_table('models', schema=None) as batch_op:
        batch_op.create_index(_PROMOTED_INDEX, ['component'], unique=True, sqlite_where=_PROMOTED_WHERE)


def upgrade() -> None:
    with op.batch_alter_table('models', schema=None) as batch_op:
        batch_op.drop_index(_PROMOTED_INDEX, sqlite_where=_PROMOTED_WHERE)
        batch_op.add_column(sa.Column('version', sa.String(length=200), nullable=True))
        batch_op.add_column(sa.Column('demoted_at', sa.DateTime(), nullable=True))
        batch_op.add_column(sa.Column('previous_model_id', sa.Integer(), nullable=True))
        batch_op.create_foreign_key(batch_op.f('fk_models_previous_model_id_models'), 'models',
                                    ['previous_model_id'], ['id'], ondelete='SET NULL')
    _recreate_promoted_index()

    with op.batch_alter_table('runs', schema=None) as batch_op:
        batch_op.add_column(sa.Column('first_inference_at', sa.DateTime(), nullable=True))
        batch_op.add_column(sa.Column('loop_closure_s', sa.Float(), nullable=True))


def downgrade() -> None:
    # Not batch mode for `runs`: copying it means DROP TABLE runs, and with foreign keys on (they
    # are, and a PRAGMA cannot change that inside the migration's transaction) that deletes every
    # run_events row (ON DELETE CASCADE) and nulls models.run_id. SQLite >= 3.35 drops a plain
    # nullable column in place.
    op.execute('ALTER TABLE runs DROP COLUMN loop_closure_s')
    op.execute('ALTER TABLE runs DROP COLUMN first_inference_at')

    with op.batch_alter_table('models', schema=None) as batch_op:
        batch_op.drop_index(_PROMOTED_INDEX, sqlite_where=_PROMOTED_WHERE)
        batch_op.drop_constraint(batch_op.f('fk_models_previous_model_id_models'), type_='foreignkey')
        batch_op.drop_column('previous_model_id')
        batch_op.drop_column('demoted_at')
        batch_op.drop_column('version')
    _recreate_promoted_index()
