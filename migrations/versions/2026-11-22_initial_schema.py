"""initial schema

Revision ID: 0001
Revises:
Create Date: 2026-11-22 01:08:14.705769
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0001'
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table('admin_audit',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('action', sa.String(length=48), nullable=False),
    sa.Column('study_id', sa.Integer(), nullable=True),
    sa.Column('participant_public_id', sa.String(length=32), nullable=True),
    sa.Column('detail', sa.JSON(), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_admin_audit'))
    )
    op.create_table('admin_credential',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('token_hash', sa.String(length=64), nullable=False),
    sa.Column('active', sa.Boolean(), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.Column('revoked_at', sa.DateTime(timezone=True), nullable=True),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_admin_credential')),
    sa.UniqueConstraint('token_hash', name=op.f('uq_admin_credential_token_hash'))
    )
    op.create_table('app_secret',
    sa.Column('name', sa.String(length=64), nullable=False),
    sa.Column('value', sa.String(length=128), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.PrimaryKeyConstraint('name', name=op.f('pk_app_secret'))
    )
    op.create_table('study',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('slug', sa.String(length=64), nullable=False),
    sa.Column('title', sa.String(length=200), nullable=False),
    sa.Column('status', sa.String(length=16), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_study')),
    sa.UniqueConstraint('slug', name=op.f('uq_study_slug'))
    )
    op.create_table('study_version',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('study_id', sa.Integer(), nullable=False),
    sa.Column('version', sa.Integer(), nullable=False),
    sa.Column('config', sa.JSON(), nullable=False),
    sa.Column('config_hash', sa.String(length=64), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.Column('frozen_at', sa.DateTime(timezone=True), nullable=True),
    sa.ForeignKeyConstraint(['study_id'], ['study.id'], name=op.f('fk_study_version_study_id_study'),
                            ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_study_version')),
    sa.UniqueConstraint('study_id', 'version', name=op.f('uq_study_version_study_id_version'))
    )
    with op.batch_alter_table('study_version', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_study_version_study_id'), ['study_id'], unique=False)

    op.create_table('participant',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('public_id', sa.String(length=32), nullable=False),
    sa.Column('token_hash', sa.String(length=64), nullable=False),
    sa.Column('study_id', sa.Integer(), nullable=False),
    sa.Column('study_version_id', sa.Integer(), nullable=False),
    sa.Column('external_id', sa.String(length=200), nullable=True),
    sa.Column('recruitment', sa.JSON(), nullable=False),
    sa.Column('status', sa.String(length=16), nullable=False),
    sa.Column('step', sa.JSON(), nullable=False),
    sa.Column('block_order', sa.JSON(), nullable=True),
    sa.Column('assignment', sa.JSON(), nullable=True),
    sa.Column('score', sa.Float(), nullable=False),
    sa.Column('beliefs', sa.JSON(), nullable=False),
    sa.Column('completion_code', sa.String(length=64), nullable=True),
    sa.Column('compensation', sa.Float(), nullable=True),
    sa.Column('excluded', sa.Boolean(), nullable=False),
    sa.Column('exclusion_reason', sa.Text(), nullable=True),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.Column('consented_at', sa.DateTime(timezone=True), nullable=True),
    sa.Column('started_at', sa.DateTime(timezone=True), nullable=True),
    sa.Column('finished_at', sa.DateTime(timezone=True), nullable=True),
    sa.Column('last_seen_at', sa.DateTime(timezone=True), nullable=False),
    sa.ForeignKeyConstraint(['study_id'], ['study.id'], name=op.f('fk_participant_study_id_study'), ondelete='CASCADE'),
    sa.ForeignKeyConstraint(['study_version_id'], ['study_version.id'],
                            name=op.f('fk_participant_study_version_id_study_version')),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_participant')),
    sa.UniqueConstraint('public_id', name=op.f('uq_participant_public_id')),
    sa.UniqueConstraint('study_id', 'external_id', name=op.f('uq_participant_study_id_external_id')),
    sa.UniqueConstraint('token_hash', name=op.f('uq_participant_token_hash'))
    )
    with op.batch_alter_table('participant', schema=None) as batch_op:
        batch_op.create_index('ix_participant_study_status', ['study_id', 'status'], unique=False)

    op.create_table('answer',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('participant_id', sa.Integer(), nullable=False),
    sa.Column('study_version_id', sa.Integer(), nullable=False),
    sa.Column('context', sa.String(length=64), nullable=False),
    sa.Column('block', sa.Integer(), nullable=True),
    sa.Column('block_name', sa.String(length=64), nullable=True),
    sa.Column('shelf', sa.Integer(), nullable=True),
    sa.Column('questionnaire', sa.String(length=64), nullable=False),
    sa.Column('item', sa.String(length=64), nullable=False),
    sa.Column('value', sa.Float(), nullable=False),
    sa.Column('scored_value', sa.Float(), nullable=False),
    sa.Column('belief', sa.Float(), nullable=True),
    sa.Column('answered_at', sa.DateTime(timezone=True), nullable=False),
    sa.ForeignKeyConstraint(['participant_id'], ['participant.id'], name=op.f('fk_answer_participant_id_participant'),
                            ondelete='CASCADE'),
    sa.ForeignKeyConstraint(['study_version_id'], ['study_version.id'],
                            name=op.f('fk_answer_study_version_id_study_version')),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_answer')),
    sa.UniqueConstraint('participant_id', 'context', 'questionnaire', 'item',
                        name=op.f('uq_answer_participant_id_context_questionnaire_item'))
    )
    with op.batch_alter_table('answer', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_answer_participant_id'), ['participant_id'], unique=False)

    op.create_table('event',
    sa.Column('id', sa.BigInteger().with_variant(sa.Integer(), 'sqlite'), nullable=False),
    sa.Column('study_id', sa.Integer(), nullable=False),
    sa.Column('participant_id', sa.Integer(), nullable=True),
    sa.Column('kind', sa.String(length=48), nullable=False),
    sa.Column('payload', sa.JSON(), nullable=False),
    sa.Column('client_time_ms', sa.Float(), nullable=True),
    sa.Column('server_monotonic_s', sa.Float(), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.ForeignKeyConstraint(['participant_id'], ['participant.id'], name=op.f('fk_event_participant_id_participant'),
                            ondelete='CASCADE'),
    sa.ForeignKeyConstraint(['study_id'], ['study.id'], name=op.f('fk_event_study_id_study'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_event'))
    )
    with op.batch_alter_table('event', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_event_participant_id'), ['participant_id'], unique=False)
        batch_op.create_index(batch_op.f('ix_event_study_id'), ['study_id'], unique=False)

    op.create_table('idempotent_response',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('participant_id', sa.Integer(), nullable=False),
    sa.Column('key', sa.String(length=128), nullable=False),
    sa.Column('request_hash', sa.String(length=64), nullable=False),
    sa.Column('response', sa.JSON(), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.ForeignKeyConstraint(['participant_id'], ['participant.id'],
                            name=op.f('fk_idempotent_response_participant_id_participant'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_idempotent_response')),
    sa.UniqueConstraint('participant_id', 'key', name=op.f('uq_idempotent_response_participant_id_key'))
    )
    op.create_table('trial',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('participant_id', sa.Integer(), nullable=False),
    sa.Column('study_version_id', sa.Integer(), nullable=False),
    sa.Column('practice', sa.Boolean(), nullable=False),
    sa.Column('block', sa.Integer(), nullable=False),
    sa.Column('block_name', sa.String(length=64), nullable=False),
    sa.Column('policy', sa.String(length=32), nullable=False),
    sa.Column('trial', sa.Integer(), nullable=False),
    sa.Column('trial_overall', sa.Integer(), nullable=False),
    sa.Column('shelf', sa.Integer(), nullable=False),
    sa.Column('complexity', sa.String(length=8), nullable=False),
    sa.Column('robot_action', sa.String(length=8), nullable=False),
    sa.Column('stage', sa.String(length=16), nullable=False),
    sa.Column('human_action', sa.String(length=16), nullable=True),
    sa.Column('outcome', sa.String(length=8), nullable=True),
    sa.Column('experience', sa.String(length=8), nullable=True),
    sa.Column('reward', sa.Float(), nullable=True),
    sa.Column('score', sa.Float(), nullable=True),
    sa.Column('belief_before', sa.Float(), nullable=False),
    sa.Column('belief_after', sa.Float(), nullable=True),
    sa.Column('policy_belief', sa.Float(), nullable=True),
    sa.Column('decision_deadline_at', sa.DateTime(timezone=True), nullable=True),
    sa.Column('attempt_end_at', sa.DateTime(timezone=True), nullable=True),
    sa.Column('teleop_deadline_at', sa.DateTime(timezone=True), nullable=True),
    sa.Column('decision_time_ms', sa.Float(), nullable=True),
    sa.Column('teleop_time_ms', sa.Float(), nullable=True),
    sa.Column('teleop_success', sa.Boolean(), nullable=True),
    sa.Column('failure_mode', sa.String(length=16), nullable=True),
    sa.Column('started_at', sa.DateTime(timezone=True), nullable=False),
    sa.Column('decided_at', sa.DateTime(timezone=True), nullable=True),
    sa.Column('completed_at', sa.DateTime(timezone=True), nullable=True),
    sa.ForeignKeyConstraint(['participant_id'], ['participant.id'], name=op.f('fk_trial_participant_id_participant'),
                            ondelete='CASCADE'),
    sa.ForeignKeyConstraint(['study_version_id'], ['study_version.id'],
                            name=op.f('fk_trial_study_version_id_study_version')),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_trial')),
    sa.UniqueConstraint('participant_id', 'practice', 'block', 'trial',
                        name=op.f('uq_trial_participant_id_practice_block_trial'))
    )
    with op.batch_alter_table('trial', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_trial_participant_id'), ['participant_id'], unique=False)
        batch_op.create_index('ix_trial_stage', ['stage'], unique=False)



def downgrade() -> None:
    with op.batch_alter_table('trial', schema=None) as batch_op:
        batch_op.drop_index('ix_trial_stage')
        batch_op.drop_index(batch_op.f('ix_trial_participant_id'))

    op.drop_table('trial')
    op.drop_table('idempotent_response')
    with op.batch_alter_table('event', schema=None) as batch_op:
        batch_op.drop_index(batch_op.f('ix_event_study_id'))
        batch_op.drop_index(batch_op.f('ix_event_participant_id'))

    op.drop_table('event')
    with op.batch_alter_table('answer', schema=None) as batch_op:
        batch_op.drop_index(batch_op.f('ix_answer_participant_id'))

    op.drop_table('answer')
    with op.batch_alter_table('participant', schema=None) as batch_op:
        batch_op.drop_index('ix_participant_study_status')

    op.drop_table('participant')
    with op.batch_alter_table('study_version', schema=None) as batch_op:
        batch_op.drop_index(batch_op.f('ix_study_version_study_id'))

    op.drop_table('study_version')
    op.drop_table('study')
    op.drop_table('app_secret')
    op.drop_table('admin_credential')
    op.drop_table('admin_audit')
