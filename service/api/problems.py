"""Errors as RFC 9457 problem details (application/problem+json)."""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.errors import InputError

PROBLEM = "application/problem+json"


def problem(status: int, title: str, detail: str, type_: str = "about:blank", **extra) -> JSONResponse:
    return JSONResponse({"type": type_, "title": title, "status": status, "detail": detail, **extra},
                        status_code=status, media_type=PROBLEM)


class ProblemError(Exception):
    """Raised by routes and dependencies to answer with a problem body (status, title, detail)."""

    def __init__(self, status: int, title: str, detail: str, headers: dict[str, str] | None = None, **extra) -> None:
        super().__init__(detail)
        self.status, self.title, self.detail, self.headers, self.extra = status, title, detail, headers, extra


def install(app: FastAPI) -> None:
    @app.exception_handler(ProblemError)
    async def _problem(request: Request, exc: ProblemError):
        response = problem(exc.status, exc.title, exc.detail, instance=str(request.url.path), **exc.extra)
        for k, v in (exc.headers or {}).items():
            response.headers[k] = v
        return response

    @app.exception_handler(InputError)
    async def _input(request: Request, exc: InputError):
        return problem(422, "Unusable input", str(exc), instance=str(request.url.path))

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        errs = exc.errors()
        first = errs[0] if errs else {"loc": (), "msg": "invalid request"}
        where = ".".join(str(x) for x in first["loc"])
        detail = f"{where}: {first['msg']}"
        if first.get("type") == "json_invalid":  # the body is no JSON document: say where it breaks
            at = first["loc"][1] if len(first["loc"]) > 1 else None
            ctx = first.get("ctx")
            why = ctx.get("error", "") if isinstance(ctx, dict) else ""
            detail = (f"body: not valid JSON{f' at character {at}' if at is not None else ''}"
                      f"{f' ({why})' if why else ''}; send one JSON object with Content-Type: application/json")
        return problem(422, "Invalid request", detail, instance=str(request.url.path),
                       errors=[{"loc": list(map(str, e["loc"])), "msg": e["msg"]} for e in errs])

    @app.exception_handler(Exception)
    async def _internal(request: Request, exc: Exception):  # the server still logs the traceback
        return problem(500, "Internal Server Error", f"the service failed on this request ({type(exc).__name__});"
                       " the service log has the details", instance=str(request.url.path))

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        return problem(exc.status_code, str(exc.detail), str(exc.detail), instance=str(request.url.path))
