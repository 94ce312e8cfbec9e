"""the scene proven on screen: which view showed it, and the page's time of the frame; a teleoperation's wait for
the page's view

Revision ID: 0009
Revises: 0008
Create Date: 2026-12-05 00:00:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0009'
down_revision = '0008'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('trial', schema=None) as batch_op:
        batch_op.add_column(sa.Column('scene_shown_view', sa.String(length=8), nullable=True))
        batch_op.add_column(sa.Column('scene_shown_client_ms', sa.Float(), nullable=True))
        batch_op.add_column(sa.Column('teleop_view_wait_ms', sa.Float(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table('trial', schema=None) as batch_op:
        batch_op.drop_column('teleop_view_wait_ms')
        batch_op.drop_column('scene_shown_client_ms')
        batch_op.drop_column('scene_shown_view')
