"""fitted models (the model registry) and the provenance columns of trials

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-22 03:31:12.938301
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0002'
down_revision = '0001'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table('fitted_model',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('study_id', sa.Integer(), nullable=False),
    sa.Column('fit_key', sa.String(length=64), nullable=False),
    sa.Column('status', sa.String(length=16), nullable=False),
    sa.Column('error', sa.Text(), nullable=True),
    sa.Column('restarts', sa.Integer(), nullable=False),
    sa.Column('seed', sa.BigInteger(), nullable=False),
    sa.Column('p_high', sa.Float(), nullable=False),
    sa.Column('data_hash', sa.String(length=64), nullable=False),
    sa.Column('study_versions', sa.JSON(), nullable=False),
    sa.Column('participants', sa.JSON(), nullable=False),
    sa.Column('n_trials', sa.Integer(), nullable=False),
    sa.Column('code_version', sa.String(length=64), nullable=False),
    sa.Column('progress_done', sa.Integer(), nullable=False),
    sa.Column('progress_total', sa.Integer(), nullable=False),
    sa.Column('document', sa.JSON(), nullable=True),
    sa.Column('content_hash', sa.String(length=64), nullable=True),
    sa.Column('loglik', sa.Float(), nullable=True),
    sa.Column('policy', sa.JSON(), nullable=True),
    sa.Column('agnostic', sa.JSON(), nullable=True),
    sa.Column('evaluation_studies', sa.JSON(), nullable=False),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.Column('finished_at', sa.DateTime(timezone=True), nullable=True),
    sa.ForeignKeyConstraint(['study_id'], ['study.id'], name=op.f('fk_fitted_model_study_id_study'),
                            ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_fitted_model'))
    )
    with op.batch_alter_table('fitted_model', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_fitted_model_content_hash'), ['content_hash'], unique=False)
        batch_op.create_index(batch_op.f('ix_fitted_model_fit_key'), ['fit_key'], unique=False)
        batch_op.create_index(batch_op.f('ix_fitted_model_study_id'), ['study_id'], unique=False)

    with op.batch_alter_table('trial', schema=None) as batch_op:
        batch_op.add_column(sa.Column('model_hash', sa.String(length=64), nullable=True))
        batch_op.add_column(sa.Column('policy_hash', sa.String(length=64), nullable=True))
        batch_op.add_column(sa.Column('seed', sa.BigInteger(), nullable=True))



def downgrade() -> None:
    with op.batch_alter_table('trial', schema=None) as batch_op:
        batch_op.drop_column('seed')
        batch_op.drop_column('policy_hash')
        batch_op.drop_column('model_hash')

    with op.batch_alter_table('fitted_model', schema=None) as batch_op:
        batch_op.drop_index(batch_op.f('ix_fitted_model_study_id'))
        batch_op.drop_index(batch_op.f('ix_fitted_model_fit_key'))
        batch_op.drop_index(batch_op.f('ix_fitted_model_content_hash'))

    op.drop_table('fitted_model')
