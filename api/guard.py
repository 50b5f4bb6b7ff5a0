"""What every request meets before a route: a cap on its body, no control characters in its path or
query, a limit on failed logins per client, and the page's security headers.

A plain ASGI middleware (not Starlette's BaseHTTPMiddleware), so it reads the body as it streams in
and answers 413 as soon as the cap is passed, before anything parses it, chunked bodies included.
"""

from __future__ import annotations

import json
import threading
import time
from collections import defaultdict, deque
from collections.abc import Awaitable, Callable, MutableMapping
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import unquote_to_bytes

from api.problems import PROBLEM_MEDIA_TYPE, TITLES

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

BODY_MAX_BYTES = 1 << 20
"""Largest request body [bytes]: a run request is a few hundred bytes, a model file a few kB."""
LOGIN_FAILURES_MAX = 10
"""Failed key checks (POST /session, or a bearer key that is unknown or revoked) a client may make per
LOGIN_WINDOW_S before its key checks are answered 429."""
LOGIN_WINDOW_S = 60.0
LOGIN_BUCKETS_MAX = 10_000  # (client, key id) pairs remembered at once; the oldest go first
SESSION_PATH = "/api/v1/session"
CSP = (
    "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data: blob:;"
    " connect-src 'self'; font-src 'self'; object-src 'none'; base-uri 'none'; form-action 'self';"
    " frame-ancestors 'none'"
)
"""The page's Content-Security-Policy: its own scripts and styles only (no inline script), no framing."""
NO_CSP_PATHS = ("/docs", "/redoc")  # FastAPI's API explorers load their scripts from a CDN, inline


def _control_byte(data: bytes) -> int | None:
    """The first control character (C0 or DEL) in `data`, if any."""
    for byte in data:
        if byte < 0x20 or byte == 0x7F:
            return byte
    return None


def _is_json(content_type: bytes) -> bool:
    media = content_type.split(b";", 1)[0].strip().lower()
    return media == b"application/json" or (media.startswith(b"application/") and media.endswith(b"+json"))


def key_bucket(token: str) -> str:
    """What failures are counted under, beside the client's address: the key id a key presents (the part
    before its '.'), or '' for anything else. So failures against one key's id hold back further tries at
    that key, and a flood of made-up keys shares one bucket, without locking out a client whose own key
    is good (on loopback every client has the same address)."""
    head, dot, _ = token.partition(".")
    return head[:32] if dot and head.isalnum() else ""


def _bearer(headers: dict[str, bytes]) -> str:
    scheme, _, token = headers.get("authorization", b"").decode("latin-1").partition(" ")
    return token.strip() if scheme.lower() == "bearer" else ""


def _login_key(body: bytes) -> str:
    try:
        key = json.loads(body).get("key")
    except (ValueError, AttributeError):
        return ""
    return key if isinstance(key, str) else ""


@dataclass
class LoginLimit:
    """Failed key checks per (client, key id) in a sliding window (thread-safe: routes run on threads)."""

    failures_max: int = LOGIN_FAILURES_MAX
    window_s: float = LOGIN_WINDOW_S
    clock: Callable[[], float] = time.monotonic
    _failed: dict[tuple[str, str], deque[float]] = field(default_factory=lambda: defaultdict(deque))
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def _trim(self, client: tuple[str, str], now: float) -> deque[float]:
        failed = self._failed[client]
        while failed and failed[0] <= now - self.window_s:
            failed.popleft()
        if not failed:
            del self._failed[client]  # a client that stopped failing leaves no entry behind
            return deque()
        return failed

    def retry_after_s(self, client: tuple[str, str]) -> int | None:
        """Seconds until `client` may try a key again (None: now)."""
        with self._lock:
            now = self.clock()
            failed = self._trim(client, now)
            if len(failed) < self.failures_max:
                return None
            return max(1, int(failed[-self.failures_max] + self.window_s - now + 0.999))

    def forget(self) -> None:
        """Every failure forgotten (a fresh window for every client)."""
        with self._lock:
            self._failed.clear()

    def failed(self, client: tuple[str, str]) -> None:
        with self._lock:
            if client not in self._failed and len(self._failed) >= LOGIN_BUCKETS_MAX:
                del self._failed[next(iter(self._failed))]  # the longest remembered
            self._failed[client].append(self.clock())


async def _problem(send: Send, status: int, detail: str, headers: dict[str, str] | None = None) -> None:
    body = json.dumps(
        {
            "type": f"https://hdrig.invalid/problems/{status}",
            "title": TITLES.get(status, "Error"),
            "status": status,
            "detail": detail,
        }
    ).encode()
    raw = [
        (b"content-type", PROBLEM_MEDIA_TYPE.encode()),
        (b"content-length", str(len(body)).encode()),
        (b"x-content-type-options", b"nosniff"),
        (b"connection", b"close"),  # a body left unread must not be taken for the next request
    ]
    raw += [(k.lower().encode(), v.encode()) for k, v in (headers or {}).items()]
    await send({"type": "http.response.start", "status": status, "headers": raw})
    await send({"type": "http.response.body", "body": body})


class Guard:
    """The middleware; `limit` is shared with the app (`app.state.login_limit`) so tests can set it."""

    def __init__(self, app: ASGIApp, limit: LoginLimit, body_max_bytes: int = BODY_MAX_BYTES) -> None:
        self.app, self.limit, self.body_max_bytes = app, limit, body_max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        path: str = scope.get("path", "")
        raw_query: bytes = scope.get("query_string", b"")
        bad = _control_byte(path.encode("utf-8", "surrogateescape"))
        if bad is None:
            bad = _control_byte(unquote_to_bytes(raw_query))
        if bad is None:
            bad = _control_byte(raw_query)
        if bad is not None:
            where = "path" if _control_byte(path.encode("utf-8", "surrogateescape")) is not None else "query"
            await _problem(send, 400, f"the {where} holds a control character (byte 0x{bad:02x})")
            return

        headers = {k.decode("latin-1").lower(): v for k, v in scope.get("headers", [])}
        address = (scope.get("client") or ("?", 0))[0]
        login = path == SESSION_PATH and scope["method"] == "POST"
        checks_key = "authorization" in headers or login

        length = headers.get("content-length")
        if length is not None:
            try:
                declared = int(length)
            except ValueError:
                await _problem(send, 400, "Content-Length is not a number of bytes")
                return
            if declared > self.body_max_bytes:
                await _problem(send, 413, self._too_large())
                return
        if scope["method"] in ("POST", "PUT", "PATCH", "DELETE") and (
            length is not None or b"chunked" in headers.get("transfer-encoding", b"").lower()
        ):
            chunks: list[bytes] = []
            size = 0
            while True:
                message = await receive()
                if message["type"] == "http.disconnect":
                    return
                chunk = message.get("body", b"")
                size += len(chunk)
                if size > self.body_max_bytes:
                    await _problem(send, 413, self._too_large())
                    return
                chunks.append(chunk)
                if not message.get("more_body", False):
                    break
            body = b"".join(chunks)
            if body and path.startswith("/api/") and not _is_json(headers.get("content-type", b"")):
                await _problem(send, 415, "the request body must be JSON (Content-Type: application/json)")
                return
            replayed = False

            async def replay() -> Message:
                nonlocal replayed
                if not replayed:
                    replayed = True
                    return {"type": "http.request", "body": body, "more_body": False}
                return await receive()  # after the body: the disconnect, when it comes

            receive = replay
        else:
            body = b""

        client = (address, "")
        if checks_key:  # which key is tried: the login's in its body, else the bearer's
            client = (address, key_bucket(_login_key(body) if login else _bearer(headers)))
            wait_s = self.limit.retry_after_s(client)
            if wait_s is not None:
                await _problem(
                    send,
                    429,
                    f"too many failed key checks from this client; try again in {wait_s} s",
                    {"Retry-After": str(wait_s)},
                )
                return

        html = not path.startswith("/api/") and not path.startswith(NO_CSP_PATHS)

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                if checks_key and message["status"] == 401:
                    self.limit.failed(client)
                extra = [(b"x-content-type-options", b"nosniff"), (b"x-frame-options", b"DENY")]
                if html:
                    extra.append((b"content-security-policy", CSP.encode()))
                    extra.append((b"referrer-policy", b"no-referrer"))
                message["headers"] = [*message.get("headers", []), *extra]
            await send(message)

        await self.app(scope, receive, send_with_headers)

    def _too_large(self) -> str:
        return f"the request body is larger than {self.body_max_bytes} bytes"
