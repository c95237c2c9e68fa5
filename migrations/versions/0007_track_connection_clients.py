"""Who holds each open /track connection: its client's address and API key

Revision ID: 0007
Revises: 0006
Create Date: 2026-12-04 12:00:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op


revision: str = '0007'
down_revision: str | None = '0006'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # Rows of connections opened before have neither: they count for no address and no key.
    with op.batch_alter_table('track_connections') as batch:
        batch.add_column(sa.Column('client_address', sa.String(length=64), nullable=True))
        batch.add_column(sa.Column('key_id', sa.Integer(), nullable=True))
        batch.create_index(batch.f('ix_track_connections_client_address'), ['client_address'], unique=False)
        batch.create_index(batch.f('ix_track_connections_key_id'), ['key_id'], unique=False)


def downgrade() -> None:
    with op.batch_alter_table('track_connections') as batch:
        batch.drop_index(batch.f('ix_track_connections_key_id'))
        batch.drop_index(batch.f('ix_track_connections_client_address'))
        batch.drop_column('key_id')
        batch.drop_column('client_address')
