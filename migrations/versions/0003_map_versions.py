"""Earlier maps of each environment, to restore one

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-27 19:00:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op


revision: str = '0003'
down_revision: str | None = '0002'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table('map_versions',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('environment_id', sa.Integer(), nullable=False),
    sa.Column('frame', sa.String(length=16), nullable=False),
    sa.Column('n_targets', sa.Integer(), nullable=False),
    sa.Column('survey_job_id', sa.String(length=32), nullable=True),
    sa.Column('document', sa.JSON(), nullable=False),
    sa.Column('replaced_by', sa.String(length=16), nullable=False),
    sa.Column('replaced_at', sa.DateTime(timezone=True), nullable=False),
    sa.ForeignKeyConstraint(['environment_id'], ['environments.id'], name=op.f('fk_map_versions_environment_id_environments'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_map_versions')),
    sqlite_autoincrement=True,
    )
    with op.batch_alter_table('map_versions', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_map_versions_environment_id'), ['environment_id'], unique=False)


def downgrade() -> None:
    with op.batch_alter_table('map_versions', schema=None) as batch_op:
        batch_op.drop_index(batch_op.f('ix_map_versions_environment_id'))
    op.drop_table('map_versions')
