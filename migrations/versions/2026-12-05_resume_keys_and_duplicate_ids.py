"""resume keys and duplicate external ids: an external id identifies a participant, it is no key to a session

Revision ID: 0008
Revises: 0007
Create Date: 2026-12-05 15:00:00

- ``participant.resume_key_hash``: sha256 of the joining browser's resume key; a join with a known external id
  resumes that session only with it (or the same recruitment session, e.g. Prolific's SESSION_ID).
- ``participant.duplicate_of``: the public id of the study's first session with the same external id, for a second
  person who joined with it (a data-quality flag).
- ``participant.join_address_hash``: keyed hash of the joining address, kept until consent (per-address cap).
- ``(study_id, external_id)`` is no longer unique (an index instead). Sessions from before keep resuming by their
  link (the token), and by SESSION_ID / assignmentId; a join with their id alone now gets a flagged new session.
  Downgrading fails while an external id appears twice in a study (the unique constraint cannot come back).
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0008'
down_revision = '0007'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('participant', schema=None) as batch_op:
        batch_op.add_column(sa.Column('resume_key_hash', sa.String(length=64), nullable=True))
        batch_op.add_column(sa.Column('duplicate_of', sa.String(length=32), nullable=True))
        batch_op.add_column(sa.Column('join_address_hash', sa.String(length=64), nullable=True))
        batch_op.drop_constraint('uq_participant_study_id_external_id', type_='unique')
        batch_op.create_index('ix_participant_study_external_id', ['study_id', 'external_id'], unique=False)


def downgrade() -> None:
    with op.batch_alter_table('participant', schema=None) as batch_op:
        batch_op.drop_index('ix_participant_study_external_id')
        batch_op.create_unique_constraint('uq_participant_study_id_external_id', ['study_id', 'external_id'])
        batch_op.drop_column('join_address_hash')
        batch_op.drop_column('duplicate_of')
        batch_op.drop_column('resume_key_hash')
