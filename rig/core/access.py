"""Who may do what: API keys and the audit log, kept in the store's catalog (tables `keys`, `audit`).

A key is a random token shown once at creation and stored only as its SHA-256 (a high-entropy token
needs no slow hash); a presented token is checked against every live key with a constant-time compare.
Roles are ordered: a viewer reads; an operator also starts, aborts and stops (anything that moves a
motor) and starts fits; an admin also manages keys. The command line (`hdrig keys`) and the service
share these functions.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
from datetime import UTC, datetime
from enum import StrEnum
from typing import Any

import sqlalchemy as sa
from pydantic import BaseModel, Field

from model.errors import UserInputError
from rig.catalog import audit as audit_table
from rig.catalog import keys as keys_table
from rig.store import RunStore

KEY_BYTES = 32  # 256 bits of randomness: a SHA-256 of it cannot be searched
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._@-]{0,63}")


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


def create_key(store: RunStore, role: Role | str, name: str | None = None) -> str:
    """A new key of `role` named `name` (default `<role>-<n>`); returns the token, shown only this once."""
    try:
        role = Role(role)
    except ValueError:
        raise UserInputError(f"role {role!r}: use one of {', '.join(Role)}") from None
    token = secrets.token_urlsafe(KEY_BYTES)
    keys = keys_table
    with store.catalog.write() as db:
        if name is None:
            taken = set(db.execute(sa.select(keys.c.name)).scalars())
            n = 1
            while f"{role}-{n}" in taken:
                n += 1
            name = f"{role}-{n}"
        elif not NAME_PATTERN.fullmatch(name):
            raise UserInputError(
                f"key name {name!r}: 1-64 letters, digits, '.', '_', '@' or '-',"
                " starting with a letter or digit"
            )
        exists = db.execute(sa.select(keys.c.name).where(keys.c.name == name)).first() is not None
        if exists:
            raise UserInputError(f"key name {name!r} is taken (names stay taken after a revoke)")
        db.execute(keys.insert().values(name=name, role=role.value, hash=_hash(token), created=_now()))
    return token


def list_keys(store: RunStore) -> list[KeyInfo]:
    """Every key, live and revoked, oldest first."""
    keys = keys_table
    query = sa.select(keys.c.name, keys.c.role, keys.c.created, keys.c.revoked).order_by(
        keys.c.created, keys.c.name
    )
    with store.catalog.read() as db:
        rows = db.execute(query).fetchall()
    return [KeyInfo(**dict(row._mapping)) for row in rows]


def has_keys(store: RunStore) -> bool:
    """Whether any live key exists (the service makes an admin key on a store without one)."""
    keys = keys_table
    with store.catalog.read() as db:
        return db.execute(sa.select(keys.c.name).where(keys.c.revoked.is_(None)).limit(1)).first() is not None


def revoke_key(store: RunStore, name: str) -> KeyInfo:
    """Revoke a key by name: it authenticates no more (its name stays in the log and the list)."""
    keys = keys_table
    with store.catalog.write() as db:
        row = db.execute(sa.select(keys.c.name).where(keys.c.name == name)).first()
        if row is None:
            raise UserInputError(f"unknown key name {name!r}")
        db.execute(
            keys.update().where(keys.c.name == name).values(revoked=sa.func.coalesce(keys.c.revoked, _now()))
        )
    return next(k for k in list_keys(store) if k.name == name)


def authenticate(store: RunStore, token: str) -> tuple[str, Role] | None:
    """(name, role) of the live key whose token this is, else None."""
    if not token:
        return None
    digest = _hash(token)
    keys = keys_table
    with store.catalog.read() as db:
        rows = db.execute(
            sa.select(keys.c.name, keys.c.role, keys.c.hash).where(keys.c.revoked.is_(None))
        ).fetchall()
    found = None
    for row in rows:  # compare with every key, so the time taken says nothing about which matched
        if hmac.compare_digest(row.hash, digest):
            found = (row.name, Role(row.role))
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
    with store.catalog.write() as db:
        db.execute(
            audit_table.insert().values(
                time=_now(),
                who=who,
                role=None if role is None else str(role),
                action=action,
                target=target,
                detail=detail,
            )
        )


def audit_log(store: RunStore, limit: int = 1000) -> list[AuditEntry]:
    """The newest `limit` lines of the audit log, oldest first."""
    a = audit_table
    query = sa.select(a.c.time, a.c.who, a.c.role, a.c.action, a.c.target, a.c.detail)
    with store.catalog.read() as db:
        rows = db.execute(query.order_by(a.c.id.desc()).limit(limit)).fetchall()
    entries: list[dict[str, Any]] = [dict(row._mapping) for row in reversed(rows)]
    return [AuditEntry(**entry) for entry in entries]
