"""API tokens over HTTP (admin): make one for a LIMS or a colleague without a shell on the daemon's
host, list them, revoke one. A token's text is answered once, by POST, and kept nowhere (only its
SHA-256); each change is audited as `token.create` / `token.revoke` with the admin's token name."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request
from fastapi.encoders import jsonable_encoder
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool

from service.api.auth import Admin
from service.api.problems import ProblemError
from service.errors import InputError
from service.storage.errors import ConflictError, UnknownEntity
from service.storage.models import ApiToken
from service.storage.tokens import SCOPES

router = APIRouter(prefix="/tokens", tags=["tokens"])


class NewToken(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: Annotated[str, Field(description="1-100 letters, digits, '.', '_', '@' or '-', unique among active and "
                                           "revoked tokens", examples=["lims-reader"])]
    scopes: Annotated[list[str], Field(min_length=1, description=f"some of {', '.join(SCOPES)}; "
                                                                 "admin implies operate, operate implies read",
                                       examples=[["read"]])]


def token_json(row: ApiToken) -> dict:
    return {"name": row.name, "scopes": list(row.scopes), "created_utc": row.created_at, "created_by": row.created_by,
            "revoked_utc": row.revoked_at}


@router.post("", status_code=201)
async def create(body: NewToken, request: Request, who: Admin) -> JSONResponse:
    """A new token; its text is in this answer only (store it now: it cannot be shown again)."""
    store = request.app.state.store
    try:
        row, token = await run_in_threadpool(store.create_token, body.name, body.scopes, actor=who.name)
    except ConflictError as exc:
        raise ProblemError(409, "Token name taken", f"name: {exc}", field="name") from None
    except InputError as exc:
        field = "scopes" if str(exc).startswith("scopes") else "name"
        raise ProblemError(422, "Unusable token", str(exc), field=field) from None
    out = {**token_json(row), "token": token}
    return JSONResponse(jsonable_encoder(out), status_code=201, headers={"Location": f"/tokens/{row.name}",
                                                                 "Cache-Control": "no-store"})


@router.get("")
async def list_tokens(request: Request, _: Admin,
                      include_revoked: Annotated[bool, Query(description="list revoked tokens too")] = False) -> dict:
    """Every token's name, scopes, creation and revocation; never a token's text."""
    rows = await run_in_threadpool(request.app.state.store.tokens, include_revoked=include_revoked)
    return {"tokens": [token_json(r) for r in rows]}


@router.delete("/{name}")
async def revoke(name: str, request: Request, who: Admin) -> dict:
    """Revoke a token: requests with it are refused (401) from this answer on."""
    try:
        row = await run_in_threadpool(request.app.state.store.revoke_token, name, actor=who.name)
    except UnknownEntity as exc:
        raise ProblemError(404, "Unknown token", f"name: {exc}", field="name") from None
    cache = getattr(request.app.state, "token_cache", None)
    if cache is not None:
        cache.clear()  # the revoked token stops working now, not when its cache entry runs out
    return token_json(row)

