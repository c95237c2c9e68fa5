"""Jobs on a distributed engine (attempt, worker, heartbeat); open /track connections

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-27 23:10:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op


revision: str = '0005'
down_revision: str | None = '0004'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table('jobs') as batch:
        batch.add_column(sa.Column('attempt', sa.Integer(), nullable=False, server_default='0'))
        batch.add_column(sa.Column('worker', sa.String(length=128), nullable=True))
        batch.add_column(sa.Column('heartbeat_at', sa.DateTime(timezone=True), nullable=True))
    op.create_table('track_connections',
    sa.Column('id', sa.String(length=32), nullable=False),
    sa.Column('server', sa.String(length=96), nullable=False),
    sa.Column('environment_id', sa.Integer(), nullable=False),
    sa.Column('opened_at', sa.DateTime(timezone=True), nullable=False),
    sa.Column('seen_at', sa.DateTime(timezone=True), nullable=False),
    sa.ForeignKeyConstraint(['environment_id'], ['environments.id'], name=op.f('fk_track_connections_environment_id_environments'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_track_connections')),
    )
    op.create_index(op.f('ix_track_connections_server'), 'track_connections', ['server'], unique=False)
    op.create_index(op.f('ix_track_connections_environment_id'), 'track_connections', ['environment_id'], unique=False)
    op.create_index(op.f('ix_track_connections_seen_at'), 'track_connections', ['seen_at'], unique=False)


def downgrade() -> None:
    op.drop_index(op.f('ix_track_connections_seen_at'), table_name='track_connections')
    op.drop_index(op.f('ix_track_connections_environment_id'), table_name='track_connections')
    op.drop_index(op.f('ix_track_connections_server'), table_name='track_connections')
    op.drop_table('track_connections')
    with op.batch_alter_table('jobs') as batch:
        batch.drop_column('heartbeat_at')
        batch.drop_column('worker')
        batch.drop_column('attempt')
