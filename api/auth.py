"""Who is asking: a Bearer key, or the browser page's session cookie (with its CSRF token).

Keys live in the store (`rig.core.access`); browser sessions live in memory only (a restart logs the
page out). A session maps a random token to the key it was opened with, so revoking the key ends the
session too. Requests that change state (POST, DELETE) authenticated by the cookie must carry the
`X-CSRF-Token` header equal to the readable `hdrig_csrf` cookie; Bearer requests need none (a browser
never adds an Authorization header by itself).
"""

from __future__ import annotations

import hmac
import secrets
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import APIKeyCookie, HTTPAuthorizationCredentials, HTTPBearer

from api.problems import ProblemError
from rig.core import access
from rig.core.access import Role
from rig.store.runs import RunStore

SESSION_COOKIE = "hdrig_session"
CSRF_COOKIE = "hdrig_csrf"
CSRF_HEADER = "X-CSRF-Token"
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})

bearer_scheme = HTTPBearer(auto_error=False, description="an API key from `hdrig keys create`")
cookie_scheme = APIKeyCookie(name=SESSION_COOKIE, auto_error=False, description="the page's session")


@dataclass(frozen=True)
class Principal:
    """The caller: the key's name and role, and how it authenticated."""

    name: str
    role: Role
    via: str  # "bearer" or "cookie"


@dataclass(frozen=True)
class Session:
    key: str
    csrf: str


class Sessions:
    """Browser sessions of this process: session token → the key it was opened with."""

    def __init__(self) -> None:
        self._sessions: dict[str, Session] = {}
        self._lock = threading.Lock()

    def open(self, key: str) -> tuple[str, str]:
        token, csrf = secrets.token_urlsafe(32), secrets.token_urlsafe(32)
        with self._lock:
            self._sessions[token] = Session(key, csrf)
        return token, csrf

    def get(self, token: str) -> Session | None:
        with self._lock:
            return self._sessions.get(token)

    def close(self, token: str) -> None:
        with self._lock:
            self._sessions.pop(token, None)


def _unauthenticated(detail: str) -> ProblemError:
    return ProblemError(401, detail, headers={"WWW-Authenticate": "Bearer"})


def principal(
    request: Request,
    bearer: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer_scheme)],
    cookie: Annotated[str | None, Depends(cookie_scheme)],
) -> Principal:
    """The caller, authenticated by key or session (401 otherwise; 403 for a cookie without CSRF)."""
    store: RunStore = request.app.state.store
    if bearer is not None:
        found = access.authenticate(store, bearer.credentials)
        if found is None:
            raise _unauthenticated("the API key is unknown or revoked")
        return Principal(found[0], found[1], "bearer")
    if request.headers.get("authorization"):
        raise _unauthenticated("Authorization must be `Bearer <key>`")
    if cookie:
        sessions: Sessions = request.app.state.sessions
        session = sessions.get(cookie)
        found = access.authenticate(store, session.key) if session else None
        if session is None or found is None:
            raise _unauthenticated("the session has ended: log in again")
        if request.method not in SAFE_METHODS:
            sent = request.headers.get(CSRF_HEADER, "")
            if not hmac.compare_digest(sent.encode(), session.csrf.encode()):
                raise ProblemError(
                    403, f"a request with the session cookie that changes state needs {CSRF_HEADER}"
                )
        return Principal(found[0], found[1], "cookie")
    raise _unauthenticated("authenticate with `Authorization: Bearer <key>` (hdrig keys create)")


def require(role: Role) -> Callable[..., Principal]:
    """A dependency: the caller, who must hold at least `role` (403 otherwise)."""

    def check(who: Annotated[Principal, Depends(principal)]) -> Principal:
        if not who.role.allows(role):
            raise ProblemError(403, f"this needs the {role} role; key {who.name!r} is {who.role}")
        return who

    check.__name__ = f"require_{role}"
    return check


viewer = require(Role.VIEWER)
operator = require(Role.OPERATOR)
admin = require(Role.ADMIN)
