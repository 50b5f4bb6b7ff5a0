"""Keys salted and slow to test: a key id column, and every stored hash (an unsalted SHA-256) replaced by a
salted scrypt of it; runs keep their progress (an interrupted run says how far it got).

The keys' tokens are not known here, only their SHA-256, so the new hash is scrypt(SHA-256 hex, salt): the
same function `rig.core.access.salted_hash` computes for new keys, written out here so this migration
stays what it was whatever that code becomes. Keys made before have no key id: the service checks them
against the rows without one.
"""

from __future__ import annotations

import hashlib
import secrets

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None

SCRYPT_N, SCRYPT_R, SCRYPT_P = 2**14, 8, 1


def _salted(digest: str) -> str:
    salt = secrets.token_bytes(16)
    derived = hashlib.scrypt(
        digest.encode(), salt=salt, n=SCRYPT_N, r=SCRYPT_R, p=SCRYPT_P, maxmem=64 * 1024 * 1024, dklen=32
    )
    return f"scrypt${SCRYPT_N}${SCRYPT_R}${SCRYPT_P}${salt.hex()}${derived.hex()}"


def upgrade() -> None:
    op.add_column("keys", sa.Column("key_id", sa.Text))
    op.create_index("keys_key_id", "keys", ["key_id"], unique=True)
    op.add_column("runs", sa.Column("progress", sa.Float))
    keys = sa.table("keys", sa.column("name", sa.Text), sa.column("hash", sa.Text))
    bind = op.get_bind()
    for name, digest in bind.execute(sa.select(keys.c.name, keys.c.hash)).fetchall():
        if not digest.startswith("scrypt$"):
            bind.execute(keys.update().where(keys.c.name == name).values(hash=_salted(digest)))


def downgrade() -> None:
    # The salted hashes cannot be turned back into SHA-256: the keys made or migrated stop working.
    with op.batch_alter_table("runs") as runs:
        runs.drop_column("progress")
    op.drop_index("keys_key_id", table_name="keys")
    with op.batch_alter_table("keys") as keys:
        keys.drop_column("key_id")
