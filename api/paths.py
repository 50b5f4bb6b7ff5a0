"""Server paths never leave the service: every JSON answer is rewritten before it is sent.

Run documents, job results and error messages carry paths of the server's files (the run's data file and
folder, artifacts, a fit's report, a model file named by a command line). A client names runs by id,
models by name and files relative to their run or job, so it needs none of them, and a path tells a
viewer how the server is laid out. A path inside the store becomes relative to the store
(`runs/<id>/data.parquet`), an uploaded model its name, and any other absolute path its file name.
Streams (events, downloads) pass untouched: only `application/json` and `application/problem+json`
bodies are read.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
from pathlib import Path
from typing import Any

from starlette.types import ASGIApp, Message, Receive, Scope, Send

JSON_TYPES = (b"application/json", b"application/problem+json")
# An absolute POSIX path inside a longer text: a slash after the start, a space, a quote or a paren.
EMBEDDED = re.compile(r"(?:(?<=^)|(?<=[\s'\"(=]))(/[^\s'\"),;]+)")


class PathScrubber:
    """Rewrites the server's paths in a value (see the module doc)."""

    def __init__(self, store_home: Path, models_dir: Path) -> None:
        self.homes = sorted({str(store_home), str(store_home.resolve())}, key=len, reverse=True)
        self.models = sorted({str(models_dir), str(models_dir.resolve())}, key=len, reverse=True)

    def path(self, text: str) -> str:
        for models in self.models:
            if text.startswith(models + os.sep) and text.endswith(".yaml"):
                return Path(text).stem
        for home in self.homes:
            if text == home:
                return "."
            if text.startswith(home + os.sep):
                return text[len(home) + 1 :]
        return Path(text).name or "."

    def text(self, text: str) -> str:
        if "/" not in text:
            return text
        if text.startswith("/") and not any(c.isspace() for c in text):
            return self.path(text)
        return EMBEDDED.sub(lambda m: self.path(m.group(1)), text)

    def value(self, value: Any) -> Any:
        if isinstance(value, str):
            return self.text(value)
        if isinstance(value, list):
            return [self.value(v) for v in value]
        if isinstance(value, dict):
            return {k: self.value(v) for k, v in value.items()}
        return value


class HideServerPaths:
    """ASGI middleware: JSON answers go out with `PathScrubber` applied; everything else untouched."""

    def __init__(self, app: ASGIApp, scrubber: PathScrubber) -> None:
        self.app, self.scrubber = app, scrubber

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start: Message | None = None
        chunks: list[bytes] = []

        async def rewrite(message: Message) -> None:
            nonlocal start
            if message["type"] == "http.response.start":
                content_type = dict(message.get("headers", [])).get(b"content-type", b"")
                if content_type.split(b";")[0].strip() in JSON_TYPES:
                    start = message  # held until the body is whole
                    return
                await send(message)
                return
            if message["type"] != "http.response.body" or start is None:
                await send(message)
                return
            chunks.append(message.get("body", b""))
            if message.get("more_body", False):
                return
            body = b"".join(chunks)
            with contextlib.suppress(ValueError):  # not JSON after all: sent as it was
                body = json.dumps(self.scrubber.value(json.loads(body)), separators=(",", ":")).encode()
            headers = [(k, v) for k, v in start.get("headers", []) if k != b"content-length"]
            headers.append((b"content-length", str(len(body)).encode()))
            await send({**start, "headers": headers})
            await send({"type": "http.response.body", "body": body, "more_body": False})

        await self.app(scope, receive, rewrite)
