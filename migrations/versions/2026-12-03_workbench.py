"""workbench: study drafts, preview sessions, free-text answers, who saved a config version

Revision ID: 0007
Revises: 0006
Create Date: 2026-12-03 09:00:00

- ``participant.preview``: a session the experimenter opened to try the study ("preview as participant"); left
  out of counterbalancing, exports, reports and fits unless asked for, and deletable.
- ``answer.text``: the answer of a free-text or single-choice item (its option's value); ``answer.value`` and
  ``answer.scored_value`` become nullable (a free-text answer has no number).
- ``study_version.author``: who saved the version (the name the designer sends, else the admin credential).
A study's ``status`` gains ``draft`` (new studies start as drafts); existing studies keep theirs.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0007'
down_revision = '0006'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('participant', schema=None) as batch_op:
        batch_op.add_column(sa.Column('preview', sa.Boolean(), server_default=sa.false(), nullable=False))
    with op.batch_alter_table('answer', schema=None) as batch_op:
        batch_op.add_column(sa.Column('text', sa.Text(), nullable=True))
        batch_op.alter_column('value', existing_type=sa.Float(), nullable=True)
        batch_op.alter_column('scored_value', existing_type=sa.Float(), nullable=True)
    with op.batch_alter_table('study_version', schema=None) as batch_op:
        batch_op.add_column(sa.Column('author', sa.String(length=120), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table('study_version', schema=None) as batch_op:
        batch_op.drop_column('author')
    with op.batch_alter_table('answer', schema=None) as batch_op:
        batch_op.alter_column('scored_value', existing_type=sa.Float(), nullable=False)
        batch_op.alter_column('value', existing_type=sa.Float(), nullable=False)
        batch_op.drop_column('text')
    with op.batch_alter_table('participant', schema=None) as batch_op:
        batch_op.drop_column('preview')
