"""A lab's fleet: runs carry their gear unit and operator, free tags, batch fits per unit; the audit log
gets a key of its own (PostgreSQL has no rowid) and samples a 64-bit count (weeks at 1 kHz).

Existing runs get their unit from the rig file recorded in their metadata (`rig_config.unit`).
"""

from __future__ import annotations

import json

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    bind = op.get_bind()
    sqlite = bind.dialect.name == "sqlite"
    op.add_column("runs", sa.Column("unit", sa.Text))
    op.add_column("runs", sa.Column("operator", sa.Text))
    op.create_index("runs_unit", "runs", ["unit"])
    op.create_index("runs_rig", "runs", ["rig"])
    op.create_index("runs_operator", "runs", ["operator"])
    op.create_table(
        "run_tags",
        sa.Column("run_id", sa.Text, sa.ForeignKey("runs.id"), primary_key=True),
        sa.Column("tag", sa.Text, primary_key=True),
    )
    op.create_index("run_tags_tag", "run_tags", ["tag"])
    op.create_table(
        "unit_fits",
        sa.Column("batch_id", sa.Text, primary_key=True),
        sa.Column("unit", sa.Text, primary_key=True),
        sa.Column("created", sa.Text, nullable=False),
        sa.Column("status", sa.Text, nullable=False),
        sa.Column("runs", sa.Text, nullable=False),
        sa.Column("result", sa.Text),
        sa.Column("error", sa.Text),
    )
    op.create_index("unit_fits_unit", "unit_fits", ["unit"])
    if sqlite:
        # SQLite cannot add a key to a table: copy it, keeping each line's rowid (its order) as the key.
        op.execute(
            "CREATE TABLE audit_new (id INTEGER PRIMARY KEY, time TEXT NOT NULL, who TEXT, role TEXT,"
            " action TEXT NOT NULL, target TEXT, detail TEXT)"
        )
        op.execute(
            "INSERT INTO audit_new (id, time, who, role, action, target, detail)"
            " SELECT rowid, time, who, role, action, target, detail FROM audit ORDER BY rowid"
        )
        op.execute("DROP TABLE audit")
        op.execute("ALTER TABLE audit_new RENAME TO audit")
    else:
        op.execute("ALTER TABLE audit ADD COLUMN id BIGSERIAL PRIMARY KEY")
        op.execute("ALTER TABLE runs ALTER COLUMN samples TYPE BIGINT")
    rows = bind.execute(sa.text("SELECT id, meta FROM runs WHERE meta LIKE '%\"unit\"%'")).fetchall()
    for run_id, meta in rows:
        unit = (json.loads(meta).get("rig_config") or {}).get("unit")
        if unit:
            bind.execute(sa.text("UPDATE runs SET unit = :u WHERE id = :id"), {"u": unit, "id": run_id})


def downgrade() -> None:
    raise NotImplementedError("the fleet columns are not undone: move the catalog aside instead")
