"""teleoperation rules and the guided practice teleoperation on trials

Revision ID: 0003
Revises: 0002
Create Date: 2026-12-01 20:30:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0003'
down_revision = '0002'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('trial', schema=None) as batch_op:
        batch_op.add_column(sa.Column('tutorial', sa.Boolean(), server_default=sa.false(), nullable=False))
        batch_op.add_column(sa.Column('teleop_tries', sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column('grasp_radius_m', sa.Float(), nullable=True))
        batch_op.add_column(sa.Column('align_radius_m', sa.Float(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table('trial', schema=None) as batch_op:
        batch_op.drop_column('align_radius_m')
        batch_op.drop_column('grasp_radius_m')
        batch_op.drop_column('teleop_tries')
        batch_op.drop_column('tutorial')
