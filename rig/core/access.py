"""Who may do what: API keys and the audit log, kept in the store's catalog (tables `keys`, `audit`).

A key is `<key id>.<secret>`, shown once at creation. The catalog keeps the key id (not secret: it finds
the one row to check) and a salted scrypt of the key's SHA-256, so a copy of the catalog gives no key
that works, and no two keys share a hash. scrypt takes tens of milliseconds, so a key verified once is
remembered by this process (its SHA-256 against the row's hash): each later request costs one indexed
read, which also sees a revoke made by another process. Keys from before the key ids (migration 0004
salted their hashes in place) have no id in the token: they are checked against the few rows without one.

The last live admin key cannot be revoked (nobody could manage keys after), nor can a key revoke itself
unless another admin remains. Every key made or revoked, by the service, the command line or the first
start, is written to the audit log in the same transaction.
Roles are ordered: a viewer reads; an operator also starts, aborts and stops (anything that moves a
motor) and starts fits; an admin also manages keys. The command line (`hdrig keys`) and the service
share these functions.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
import threading
from datetime import UTC, datetime
from enum import StrEnum
from typing import Any

import sqlalchemy as sa
from pydantic import BaseModel, Field

from model.errors import UserInputError
from rig.store.catalog import audit as audit_table
from rig.store.catalog import keys as keys_table
from rig.store.runs import RunStore

KEY_BYTES = 32  # 256 bits of randomness in the secret
KEY_ID_BYTES = 8  # the key id: 16 hex digits, unique among keys, not secret
KEY_ID_PATTERN = re.compile(r"[0-9a-f]{16}")
SALT_BYTES = 16
# scrypt's cost: 2**14 x 8 x 128 B = 16 MiB and tens of milliseconds per check (OWASP's minimum is
# N=2**17 at r=8 for passwords; a key has 256 bits of randomness, so a guess is not the threat a copy of
# the catalog is: this makes each of its hashes cost as much as a password's would to test).
SCRYPT_N, SCRYPT_R, SCRYPT_P = 2**14, 8, 1
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


class KeyConflictError(UserInputError):
    """A key change that would leave nobody able to manage keys (HTTP 409)."""


def _digest(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def salted_hash(digest: str, salt: bytes | None = None) -> str:
    """`scrypt$N$r$p$<salt hex>$<hash hex>` of a key's SHA-256 hex digest (migration 0004 uses it too)."""
    salt = secrets.token_bytes(SALT_BYTES) if salt is None else salt
    derived = hashlib.scrypt(
        digest.encode(), salt=salt, n=SCRYPT_N, r=SCRYPT_R, p=SCRYPT_P, maxmem=64 * 1024 * 1024, dklen=32
    )
    return f"scrypt${SCRYPT_N}${SCRYPT_R}${SCRYPT_P}${salt.hex()}${derived.hex()}"


def _matches(digest: str, stored: str) -> bool:
    """Whether a key whose SHA-256 is `digest` is the one `stored` (a `salted_hash`) was made from."""
    try:
        kind, n, r, p, salt, derived = stored.split("$")
        ok = kind == "scrypt"
        found = hashlib.scrypt(
            digest.encode(),
            salt=bytes.fromhex(salt),
            n=int(n),
            r=int(r),
            p=int(p),
            maxmem=64 * 1024 * 1024,
            dklen=len(derived) // 2,
        ).hex()
    except ValueError:  # not a hash this code made: no key matches it
        return False
    return ok and hmac.compare_digest(found, derived)


_verified: dict[str, str] = {}
"""SHA-256 of a key this process verified → the stored hash it matched (so scrypt runs once per key)."""
_verified_lock = threading.Lock()


def _verify(digest: str, stored: str) -> bool:
    with _verified_lock:
        known = _verified.get(digest)
    if known is not None:
        return hmac.compare_digest(known, stored)
    if not _matches(digest, stored):
        return False
    with _verified_lock:
        _verified[digest] = stored
    return True


def _key_id(token: str) -> str | None:
    head, dot, _ = token.partition(".")
    return head if dot and KEY_ID_PATTERN.fullmatch(head) else None


def create_key(
    store: RunStore,
    role: Role | str,
    name: str | None = None,
    who: str | None = None,
    who_role: Role | str | None = None,
    door: str = "command line",
) -> str:
    """A new key of `role` named `name` (default `<role>-<n>`); returns the token, shown only this once.
    The audit log gets `key.create` by `who` (None: the command line or the first start, told by `door`)."""
    return make_key(store, role, name, who, who_role, door)[1]


def make_key(
    store: RunStore,
    role: Role | str,
    name: str | None = None,
    who: str | None = None,
    who_role: Role | str | None = None,
    door: str = "command line",
) -> tuple[str, str]:
    """`create_key`, returning (the key's name, the token)."""
    try:
        role = Role(role)
    except ValueError:
        raise UserInputError(f"role {role!r}: use one of {', '.join(Role)}") from None
    if name is not None and not NAME_PATTERN.fullmatch(name):
        raise UserInputError(
            f"key name {name[:80]!r}: 1-64 letters, digits, '.', '_', '@' or '-',"
            " starting with a letter or digit"
        )
    key_id = secrets.token_hex(KEY_ID_BYTES)
    token = f"{key_id}.{secrets.token_urlsafe(KEY_BYTES)}"
    stored = salted_hash(_digest(token))  # scrypt outside the write lock: other writers do not wait for it
    keys = keys_table
    with store.catalog.write() as db:
        if name is None:
            taken = set(db.execute(sa.select(keys.c.name)).scalars())
            n = 1
            while f"{role}-{n}" in taken:
                n += 1
            name = f"{role}-{n}"
        exists = db.execute(sa.select(keys.c.name).where(keys.c.name == name)).first() is not None
        if exists:
            raise UserInputError(f"key name {name!r} is taken (names stay taken after a revoke)")
        db.execute(
            keys.insert().values(name=name, role=role.value, hash=stored, key_id=key_id, created=_now())
        )
        _audit_in(db, who, who_role, "key.create", name, f"{role.value} ({door})")
    return name, token


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


def revoke_key(
    store: RunStore,
    name: str,
    who: str | None = None,
    who_role: Role | str | None = None,
    door: str = "command line",
) -> KeyInfo:
    """Revoke a key by name: it authenticates no more (its name stays in the log and the list). Refused
    (KeyConflictError) for the last live admin key, and for a key revoking itself with no other admin."""
    keys = keys_table
    with store.catalog.write() as db:
        row = db.execute(sa.select(keys.c.role, keys.c.revoked).where(keys.c.name == name)).first()
        if row is None:
            raise UserInputError(f"unknown key name {name[:80]!r}")
        if row.revoked is None and row.role == Role.ADMIN:
            # Locked rows on PostgreSQL (SQLite's write lock is the whole catalog's): two admins revoking
            # each other at once cannot both pass this check.
            other_admins = db.execute(
                sa.select(keys.c.name)
                .where(keys.c.role == Role.ADMIN.value, keys.c.revoked.is_(None), keys.c.name != name)
                .with_for_update()
            ).fetchall()
            if not other_admins:
                itself = " (a key cannot revoke itself unless another admin remains)" if who == name else ""
                raise KeyConflictError(
                    f"key {name!r} is the last live admin key: make another admin key first{itself}"
                )
        db.execute(
            keys.update().where(keys.c.name == name).values(revoked=sa.func.coalesce(keys.c.revoked, _now()))
        )
        _audit_in(db, who, who_role, "key.revoke", name, door)
    return next(k for k in list_keys(store) if k.name == name)


def authenticate(store: RunStore, token: str) -> tuple[str, Role] | None:
    """(name, role) of the live key whose token this is, else None."""
    if not token or len(token) > 200:
        return None
    digest = _digest(token)
    keys = keys_table
    key_id = _key_id(token)
    query = sa.select(keys.c.name, keys.c.role, keys.c.hash).where(keys.c.revoked.is_(None))
    # A key with an id is the one row of that id; an older key (no id) one of the rows without one.
    query = query.where(keys.c.key_id == key_id) if key_id else query.where(keys.c.key_id.is_(None))
    with store.catalog.read() as db:
        rows = db.execute(query).fetchall()
    for row in rows:
        if _verify(digest, row.hash):
            return (row.name, Role(row.role))
    return None


def _audit_in(
    db: Any, who: str | None, role: Role | str | None, action: str, target: str | None, detail: str | None
) -> None:
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
        _audit_in(db, who, role, action, target, detail)


def audit_log(store: RunStore, limit: int = 1000) -> list[AuditEntry]:
    """The newest `limit` lines of the audit log, oldest first."""
    a = audit_table
    query = sa.select(a.c.time, a.c.who, a.c.role, a.c.action, a.c.target, a.c.detail)
    with store.catalog.read() as db:
        rows = db.execute(query.order_by(a.c.id.desc()).limit(limit)).fetchall()
    entries: list[dict[str, Any]] = [dict(row._mapping) for row in reversed(rows)]
    return [AuditEntry(**entry) for entry in entries]
