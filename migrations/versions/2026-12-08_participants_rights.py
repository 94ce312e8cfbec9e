"""the participant's rights: when a session's personal fields were erased (retention, or a withdrawal keeping data)

Revision ID: 0011
Revises: 0010
Create Date: 2026-12-08 12:00:00

- ``participant.personal_data_erased_at``: when the session's personal fields (``experiment.privacy.PERSONAL_FIELDS``:
  external id, recruitment parameters, resume key, address hash, questionnaire draft) were erased, by the study's
  retention rule or a withdrawal that keeps the data; null while they are kept. Sessions withdrawn before (their
  external id and recruitment parameters were cleared then) get their end time.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0011'
down_revision = '0010'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('participant', schema=None) as batch_op:
        batch_op.add_column(sa.Column('personal_data_erased_at', sa.DateTime(timezone=True), nullable=True))
    op.execute("UPDATE participant SET personal_data_erased_at = finished_at WHERE status = 'withdrawn'")


def downgrade() -> None:
    with op.batch_alter_table('participant', schema=None) as batch_op:
        batch_op.drop_column('personal_data_erased_at')
