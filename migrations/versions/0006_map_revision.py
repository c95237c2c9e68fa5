"""A map's revision (its ETag), and the revision each kept version had

Revision ID: 0006
Revises: 0005
Create Date: 2026-12-04 10:00:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op


revision: str = '0006'
down_revision: str | None = '0005'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # Every stored map starts at revision 1; versions kept before have none.
    with op.batch_alter_table('maps') as batch:
        batch.add_column(sa.Column('revision', sa.Integer(), nullable=False, server_default='1'))
    with op.batch_alter_table('map_versions') as batch:
        batch.add_column(sa.Column('revision', sa.Integer(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table('map_versions') as batch:
        batch.drop_column('revision')
    with op.batch_alter_table('maps') as batch:
        batch.drop_column('revision')
