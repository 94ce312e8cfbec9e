"""the participant's language: the BCP 47 tag of the language every page and message of the session is in

Revision ID: 0010
Revises: 0009
Create Date: 2026-12-08 09:00:00

- ``participant.language``: chosen once at the join from the study's ``languages`` (``experiment.languages``).
  Sessions from before saw English, the only language then: they get ``'en'``.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0010'
down_revision = '0009'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('participant', schema=None) as batch_op:
        batch_op.add_column(sa.Column('language', sa.String(length=16), server_default='en', nullable=False))


def downgrade() -> None:
    with op.batch_alter_table('participant', schema=None) as batch_op:
        batch_op.drop_column('language')
