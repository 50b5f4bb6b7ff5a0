"""Paging the catalog: the runs' listing order, newest first by (started, id), as one index.

A page is the next `limit` runs before a cursor (`started`, `id`) in that order; with the index a page
deep in a catalog of 100,000 runs is a seek, not a sort of everything before it. The index on `started`
alone (the baseline's) is dropped: the new one serves every query it served.
"""

from __future__ import annotations

from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_index("runs_started_id", "runs", ["started", "id"])
    op.drop_index("runs_started", table_name="runs")


def downgrade() -> None:
    op.create_index("runs_started", "runs", ["started"])
    op.drop_index("runs_started_id", table_name="runs")
