"""Who may do what: API keys and the audit log, kept in the store's catalog (`catalog.sqlite`).

A key is a random token shown once at creation and stored only as its SHA-256 (a high-entropy token
needs no slow hash); a presented token is checked against every live key with a constant-time compare.
Roles are ordered: a viewer reads; an operator also starts, aborts and stops (anything that moves a
motor) and starts fits; an admin also manages keys. The command line (`hdrig keys`) and the service
share these functions.
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import re
import secrets
import sqlite3
from collections.abc import Iterator
from datetime import UTC, datetime
from enum import StrEnum
from typing import Any

from pydantic import BaseModel, Field

from model.errors import UserInputError
from rig.store import RunStore

KEY_BYTES = 32  # 256 bits of randomness: a SHA-256 of it cannot be searched
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._@-]{0,63}")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS keys (
    name    TEXT NOT NULL UNIQUE,
    role    TEXT NOT NULL,
    hash    TEXT NOT NULL,
    created TEXT NOT NULL,
    revoked TEXT
);
CREATE TABLE IF NOT EXISTS audit (
    time   TEXT NOT NULL,
    who    TEXT,
    role   TEXT,
    action TEXT NOT NULL,
    target TEXT,
    detail TEXT
);
"""


class Role(StrEnum):
    VIEWER = "viewer"
    OPERATOR = "operator"
    ADMIN = "admin"

    @property
    def rank(self) -> int:
        return list(Role).index(self)

    def allows(self, needed: Role) -> bool:
        """Whether this role may do what `needed` may (roles are ordered viewer < operator < admin)."""
        return self.rank >= needed.rank


class KeyInfo(BaseModel):
    """One API key as listed (never its token)."""

    name: str = Field(description="the key's name; who the audit log says did something")
    role: Role = Field(
        description="viewer reads; operator also starts, aborts and stops; admin also manages keys"
    )
    created: str = Field(description="UTC, ISO 8601")
    revoked: str | None = Field(default=None, description="UTC, ISO 8601, when revoked; None while live")


class AuditEntry(BaseModel):
    """One line of the audit log: who did what to which target, when."""

    time: str = Field(description="UTC, ISO 8601")
    who: str | None = Field(description="the key's name (None: the command line)")
    role: str | None = Field(description="the key's role then")
    action: str = Field(description="start, abort, stop, reset, fit, gaps, key.create, key.revoke...")
    target: str | None = Field(description="the run, job or key acted on")
    detail: str | None = Field(default=None, description="what else was asked")


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


def _hash(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


@contextlib.contextmanager
def _db(store: RunStore) -> Iterator[sqlite3.Connection]:
    db = sqlite3.connect(store.catalog_path, timeout=30.0)
    db.row_factory = sqlite3.Row
    try:
        with db:
            db.executescript(_SCHEMA)
            yield db
    finally:
        db.close()


def create_key(store: RunStore, role: Role | str, name: str | None = None) -> str:
    """A new key of `role` named `name` (default `<role>-<n>`); returns the token, shown only this once."""
    try:
        role = Role(role)
    except ValueError:
        raise UserInputError(f"role {role!r}: use one of {', '.join(Role)}") from None
    token = secrets.token_urlsafe(KEY_BYTES)
    with _db(store) as db:
        if name is None:
            taken = {row["name"] for row in db.execute("SELECT name FROM keys")}
            n = 1
            while f"{role}-{n}" in taken:
                n += 1
            name = f"{role}-{n}"
        elif not NAME_PATTERN.fullmatch(name):
            raise UserInputError(
                f"key name {name!r}: 1-64 letters, digits, '.', '_', '@' or '-',"
                " starting with a letter or digit"
            )
        try:
            db.execute(
                "INSERT INTO keys (name, role, hash, created) VALUES (?, ?, ?, ?)",
                (name, role.value, _hash(token), _now()),
            )
        except sqlite3.IntegrityError:
            raise UserInputError(f"key name {name!r} is taken (names stay taken after a revoke)") from None
    return token


def list_keys(store: RunStore) -> list[KeyInfo]:
    """Every key, live and revoked, oldest first."""
    with _db(store) as db:
        rows = db.execute("SELECT name, role, created, revoked FROM keys ORDER BY created, name").fetchall()
    return [KeyInfo(**dict(row)) for row in rows]


def has_keys(store: RunStore) -> bool:
    """Whether any live key exists (the service makes an admin key on a store without one)."""
    with _db(store) as db:
        return db.execute("SELECT 1 FROM keys WHERE revoked IS NULL LIMIT 1").fetchone() is not None


def revoke_key(store: RunStore, name: str) -> KeyInfo:
    """Revoke a key by name: it authenticates no more (its name stays in the log and the list)."""
    with _db(store) as db:
        row = db.execute("SELECT name FROM keys WHERE name = ?", (name,)).fetchone()
        if row is None:
            raise UserInputError(f"unknown key name {name!r}")
        db.execute("UPDATE keys SET revoked = COALESCE(revoked, ?) WHERE name = ?", (_now(), name))
    return next(k for k in list_keys(store) if k.name == name)


def authenticate(store: RunStore, token: str) -> tuple[str, Role] | None:
    """(name, role) of the live key whose token this is, else None."""
    if not token:
        return None
    digest = _hash(token)
    with _db(store) as db:
        rows = db.execute("SELECT name, role, hash FROM keys WHERE revoked IS NULL").fetchall()
    found = None
    for row in rows:  # compare with every key, so the time taken says nothing about which matched
        if hmac.compare_digest(row["hash"], digest):
            found = (row["name"], Role(row["role"]))
    return found


def audit(
    store: RunStore,
    who: str | None,
    role: Role | str | None,
    action: str,
    target: str | None = None,
    detail: str | None = None,
) -> None:
    """Append one line to the audit log."""
    with _db(store) as db:
        db.execute(
            "INSERT INTO audit (time, who, role, action, target, detail) VALUES (?, ?, ?, ?, ?, ?)",
            (_now(), who, None if role is None else str(role), action, target, detail),
        )


def audit_log(store: RunStore, limit: int = 1000) -> list[AuditEntry]:
    """The newest `limit` lines of the audit log, oldest first."""
    with _db(store) as db:
        rows = db.execute(
            "SELECT time, who, role, action, target, detail FROM audit ORDER BY rowid DESC LIMIT ?", (limit,)
        ).fetchall()
    entries: list[dict[str, Any]] = [dict(row) for row in reversed(rows)]
    return [AuditEntry(**entry) for entry in entries]
