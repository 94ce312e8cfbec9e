"""finished_at for every ended session (abandoned sessions had none)

Revision ID: 0004
Revises: 0003
Create Date: 2026-12-02 00:00:00

Abandoned sessions get the time they were judged abandoned (their
``abandoned`` event, as the sweeper now records it), else their last-seen
time; any other ended session still without one gets its last-seen time.
Data only: the downgrade leaves the filled-in times (they are correct under
either schema).
"""

from __future__ import annotations

from alembic import op

revision = '0004'
down_revision = '0003'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.execute("""
        UPDATE participant SET finished_at = COALESCE(
            (SELECT MIN(event.created_at) FROM event
             WHERE event.participant_id = participant.id AND event.kind = 'abandoned'),
            last_seen_at)
        WHERE status = 'abandoned' AND finished_at IS NULL
    """)
    op.execute("""
        UPDATE participant SET finished_at = last_seen_at
        WHERE status IN ('completed', 'declined', 'withdrawn') AND finished_at IS NULL
    """)


def downgrade() -> None:
    pass
