"""Errors as RFC 9457 problem details (application/problem+json), with the model the OpenAPI
document declares for them (service.api.models.problem.Problem)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.api.models.problem import PROBLEM_MEDIA_TYPE
from service.errors import InputError
from service.storage.errors import UnknownEntity

PROBLEM = PROBLEM_MEDIA_TYPE


def problem(
    status: int, title: str, detail: str, type_: str = "about:blank", **extra: Any
) -> JSONResponse:
    return JSONResponse(
        {"type": type_, "title": title, "status": status, "detail": detail, **extra},
        status_code=status,
        media_type=PROBLEM,
    )


class ProblemError(Exception):
    """Raised by routes and dependencies to answer with a problem body (status, title, detail)."""

    def __init__(
        self,
        status: int,
        title: str,
        detail: str,
        headers: dict[str, str] | None = None,
        **extra: Any,
    ) -> None:
        super().__init__(detail)
        self.status, self.title, self.detail, self.headers, self.extra = (
            status,
            title,
            detail,
            headers,
            extra,
        )


def field_path(loc: Sequence[int | str]) -> str:
    """A validation error's location as the field's name: `grid.x_deg[0]` (body, query and path left
    out)."""
    parts = list(loc[1:] if loc and loc[0] in ("body", "query", "path", "header") else loc)
    out = ""
    for part in parts:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or (str(loc[0]) if loc else "")


# FastAPI's 400 for a body it could not even decode; a body that cannot be used is a 422 here, like
# any other
BODY_NOT_PARSED = "There was an error parsing the body"


def install(app: FastAPI) -> None:
    """Every error of the application as a problem: ours, FastAPI's validation, Starlette's HTTP
    errors."""

    @app.exception_handler(ProblemError)
    async def _problem(request: Request, exc: ProblemError) -> JSONResponse:
        response = problem(
            exc.status, exc.title, exc.detail, instance=str(request.url.path), **exc.extra
        )
        for name, value in (exc.headers or {}).items():
            response.headers[name] = value
        return response

    @app.exception_handler(InputError)
    async def _input(request: Request, exc: InputError) -> JSONResponse:
        return problem(422, "Unusable input", str(exc), instance=str(request.url.path))

    @app.exception_handler(UnknownEntity)  # before InputError, of which it is one
    async def _unknown(request: Request, exc: UnknownEntity) -> JSONResponse:
        return problem(404, "Not found", str(exc), instance=str(request.url.path))

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        errs = exc.errors()
        first = errs[0] if errs else {"loc": (), "msg": "invalid request"}
        where = field_path(first["loc"])
        detail = f"{where}: {first['msg']}"
        if first.get("type") == "json_invalid":  # the body is no JSON document: say where it breaks
            at = first["loc"][1] if len(first["loc"]) > 1 else None
            ctx = first.get("ctx")
            why = ctx.get("error", "") if isinstance(ctx, dict) else ""
            where = "body"
            detail = (
                f"body: not valid JSON{f' at character {at}' if at is not None else ''}"
                f"{f' ({why})' if why else ''}; send one JSON object with Content-Type: "
                "application/json"
            )
        return problem(
            422,
            "Invalid request",
            detail,
            instance=str(request.url.path),
            field=where,
            errors=[{"loc": list(map(str, err["loc"])), "msg": err["msg"]} for err in errs],
        )

    @app.exception_handler(Exception)
    # the server still logs the traceback
    async def _internal(request: Request, exc: Exception) -> JSONResponse:
        return problem(
            500,
            "Internal Server Error",
            f"the service failed on this request ({type(exc).__name__});"
            " the service log has the details",
            instance=str(request.url.path),
        )

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        # e.g. bytes that are not UTF-8 text
        if exc.status_code == 400 and exc.detail == BODY_NOT_PARSED:
            return problem(
                422,
                "Invalid request",
                "body: not valid JSON (the bytes are not UTF-8 text); send one JSON"
                " object with Content-Type: application/json",
                instance=str(request.url.path),
                field="body",
            )
        return problem(
            exc.status_code, str(exc.detail), str(exc.detail), instance=str(request.url.path)
        )
