"""Errors as RFC 9457 problem documents (`application/problem+json`), for every 4xx and 5xx the service
answers — its own, FastAPI's validation errors, Starlette's 404/405 and the core's exceptions."""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException

from model.errors import UserInputError
from model.run import RunFormatError
from rig.core.actions import ConflictError, UnknownJobError
from rig.core.worker import QueueFullError, RigBusyError, WorkerClosedError
from rig.store.runs import UnknownRunError

log = logging.getLogger(__name__)

PROBLEM_MEDIA_TYPE = "application/problem+json"
RETRY_AFTER_S = 5  # told to a client the rig is busy for: a short run's length, a poll's pace
DETAIL_MAX = 300
"""Most characters of a problem's `detail` or a field's message: what was wrong, never the input whole
(a 5 MB value quoted back would be a 5 MB answer)."""
FIELD_ERRORS_MAX = 10  # field errors listed in one answer; the detail counts the rest


def excerpt(text: str, limit: int = DETAIL_MAX) -> str:
    """`text` cut to `limit` characters, saying how much was left out; control characters escaped."""
    if any(ord(c) < 0x20 or ord(c) == 0x7F for c in text):
        text = text.encode("unicode_escape").decode("ascii")
    if len(text) <= limit:
        return text
    return f"{text[: limit - 30]}… [{len(text) - limit + 30} more characters]"


TITLES = {
    400: "Bad request",
    401: "Not authenticated",
    403: "Forbidden",
    404: "Not found",
    405: "Method not allowed",
    409: "Conflict",
    413: "Content too large",
    415: "Unsupported media type",
    422: "Invalid input",
    429: "Too many requests",
    500: "Internal server error",
    503: "Service unavailable",
}


class FieldError(BaseModel):
    field: str = Field(description="where: `body.params.hold_s`, `query.columns`...")
    message: str


class Problem(BaseModel):
    """RFC 9457 problem details: what went wrong, in one line (`detail`), naming the field or value."""

    type: str = Field(default="about:blank", description="a URI naming the kind of problem")
    title: str = Field(description="the status' short text")
    status: int = Field(description="the HTTP status code")
    detail: str = Field(description="one line: what was wrong, naming the field or value")
    errors: list[FieldError] | None = Field(default=None, description="validation: each bad field")


class ProblemError(Exception):
    """Raised by a route to answer with a problem document."""

    def __init__(
        self,
        status: int,
        detail: str,
        errors: list[FieldError] | None = None,
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(detail)
        self.status, self.detail, self.errors, self.headers = status, detail, errors, headers


def problem_response(
    status: int,
    detail: str,
    errors: list[FieldError] | None = None,
    headers: dict[str, str] | None = None,
) -> JSONResponse:
    title = TITLES.get(status, "Error")
    if errors is not None:
        kept = errors[:FIELD_ERRORS_MAX]
        errors = [FieldError(field=excerpt(e.field, 100), message=excerpt(e.message)) for e in kept]
    body = Problem(
        type=f"https://hdrig.invalid/problems/{status}" if status in TITLES else "about:blank",
        title=title,
        status=status,
        detail=excerpt(detail),
        errors=errors,
    )
    return JSONResponse(
        body.model_dump(mode="json", exclude_none=True),
        status_code=status,
        headers=headers,
        media_type=PROBLEM_MEDIA_TYPE,
    )


def _field(loc: tuple[Any, ...] | list[Any]) -> str:
    return ".".join(str(part) for part in loc)


def status_of(exc: UserInputError) -> tuple[int, dict[str, str] | None]:
    """The HTTP status of an error a user caused."""
    if isinstance(exc, UnknownRunError | UnknownJobError):
        return 404, None
    if isinstance(exc, ConflictError):
        return 409, None
    if isinstance(exc, QueueFullError):
        return 429, {"Retry-After": str(RETRY_AFTER_S)}
    if isinstance(exc, RigBusyError):
        return 409, {"Retry-After": str(RETRY_AFTER_S)}
    if isinstance(exc, WorkerClosedError):
        return 503, None
    if isinstance(exc, RunFormatError):
        return 409, None  # a run with no samples yet: ask again later
    return 422, None


def install(app: FastAPI) -> None:
    """Answer every error with a problem document."""

    @app.exception_handler(ProblemError)
    async def _api_problem(request: Request, exc: ProblemError) -> JSONResponse:
        return problem_response(exc.status, exc.detail, exc.errors, exc.headers)

    @app.exception_handler(UserInputError)
    async def _user_input(request: Request, exc: UserInputError) -> JSONResponse:
        status, headers = status_of(exc)
        return problem_response(status, str(exc), headers=headers)

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = [
            FieldError(field=_field(e.get("loc", ())), message=str(e.get("msg", ""))) for e in exc.errors()
        ]
        first = errors[0] if errors else FieldError(field="body", message="invalid")
        more = f" [+{len(errors) - 1} more]" if len(errors) > 1 else ""
        return problem_response(422, f"{first.field}: {first.message}{more}", errors)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        detail = exc.detail if isinstance(exc.detail, str) else TITLES.get(exc.status_code, "Error")
        if exc.status_code == 404 and detail == "Not Found":
            detail = f"no route {request.url.path}"
        elif exc.status_code == 405:
            detail = f"{request.method} is not allowed on {request.url.path}"
        return problem_response(exc.status_code, detail, headers=getattr(exc, "headers", None))

    @app.exception_handler(Exception)
    async def _bug(request: Request, exc: Exception) -> JSONResponse:
        log.exception("%s %s failed", request.method, excerpt(request.url.path))  # no raw control bytes
        return problem_response(500, f"internal error: {type(exc).__name__}")
