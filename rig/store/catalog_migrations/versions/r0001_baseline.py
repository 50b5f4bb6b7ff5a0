"""The catalog as it was before migrations: runs, checkpoints, keys, audit.

Written to create only what is missing, so a catalog made before the migrations (no `alembic_version`
table; its `keys` and `audit` tables made on first use, perhaps no `analysis` column) is upgraded in place.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None

_STATUSES = ", ".join(f"'{s}'" for s in ("running", "complete", "aborted", "interrupted"))
_DDL = [
    f"""CREATE TABLE IF NOT EXISTS runs (
    id          TEXT PRIMARY KEY,
    experiment  TEXT NOT NULL,
    rig         TEXT NOT NULL,
    model_name  TEXT,
    model_hash  TEXT,
    status      TEXT NOT NULL CHECK (status IN ({_STATUSES})),
    reason      TEXT,
    started     TEXT NOT NULL,
    ended       TEXT,
    samples     INTEGER NOT NULL DEFAULT 0,
    metrics     TEXT NOT NULL DEFAULT '{{}}',
    path        TEXT NOT NULL,
    meta        TEXT NOT NULL DEFAULT '{{}}',
    pid         INTEGER,
    host        TEXT,
    pid_started TEXT,
    analysis    TEXT
)""",
    "CREATE INDEX IF NOT EXISTS runs_started ON runs (started)",
    """CREATE TABLE IF NOT EXISTS checkpoints (
    run_id      TEXT NOT NULL REFERENCES runs (id),
    idx         INTEGER NOT NULL,
    unit        TEXT,
    t_s         REAL NOT NULL,
    estimates   TEXT NOT NULL,
    PRIMARY KEY (run_id, idx)
)""",
    "CREATE INDEX IF NOT EXISTS checkpoints_unit ON checkpoints (unit)",
    """CREATE TABLE IF NOT EXISTS keys (
    name    TEXT NOT NULL UNIQUE,
    role    TEXT NOT NULL,
    hash    TEXT NOT NULL,
    created TEXT NOT NULL,
    revoked TEXT
)""",
    """CREATE TABLE IF NOT EXISTS audit (
    time   TEXT NOT NULL,
    who    TEXT,
    role   TEXT,
    action TEXT NOT NULL,
    target TEXT,
    detail TEXT
)""",
]


def upgrade() -> None:
    for statement in _DDL:
        op.execute(statement)
    columns = {c["name"] for c in sa.inspect(op.get_bind()).get_columns("runs")}
    if "analysis" not in columns:  # a catalog from before the analysis state
        op.execute("ALTER TABLE runs ADD COLUMN analysis TEXT")


def downgrade() -> None:
    raise NotImplementedError("the baseline is not undone: move the catalog aside instead")
