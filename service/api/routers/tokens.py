"""API tokens over HTTP (admin): make one for a LIMS or a colleague without a shell on the daemon's
host, list them, revoke one. A token's text is answered once, by POST, and kept nowhere (only its
SHA-256); each change is audited as `token.create` / `token.revoke` with the admin's token name."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Query, Response
from starlette.concurrency import run_in_threadpool

from service.api.auth import Admin
from service.api.deps import TokenCacheDep, TokensRepoDep
from service.api.models.problem import READ, WRITE, problem_responses
from service.api.models.tokens import CreatedToken, NewToken, Token, Tokens
from service.api.problems import ProblemError
from service.errors import InputError
from service.storage.errors import ConflictError
from service.storage.models import ApiToken

router = APIRouter(prefix="/tokens", tags=["tokens"])


def token_body(row: ApiToken) -> Token:
    return Token(name=row.name, scopes=list(row.scopes), created_utc=row.created_at, created_by=row.created_by,
                 revoked_utc=row.revoked_at)


@router.post("", status_code=201, response_model=CreatedToken, responses=problem_responses(*WRITE, 409))
async def create(body: NewToken, response: Response, tokens: TokensRepoDep, who: Admin) -> CreatedToken:
    """A new token; its text is in this answer only (store it now: it cannot be shown again)."""
    try:
        row, token = await run_in_threadpool(tokens.create_token, body.name, body.scopes, actor=who.name)
    except ConflictError as exc:
        raise ProblemError(409, "Token name taken", f"name: {exc}", field="name") from None
    except InputError as exc:
        field = "scopes" if str(exc).startswith("scopes") else "name"
        raise ProblemError(422, "Unusable token", str(exc), field=field) from None
    response.headers["Location"] = f"/tokens/{row.name}"
    response.headers["Cache-Control"] = "no-store"
    return CreatedToken(**token_body(row).model_dump(), token=token)


@router.get("", response_model=Tokens, responses=problem_responses(*READ))
async def list_tokens(tokens: TokensRepoDep, _: Admin,
                      include_revoked: Annotated[bool, Query(description="list revoked tokens too")] = False) -> Tokens:
    """Every token's name, scopes, creation and revocation; never a token's text."""
    rows = await run_in_threadpool(tokens.all, include_revoked=include_revoked)
    return Tokens(tokens=[token_body(r) for r in rows])


@router.delete("/{name}", response_model=Token, responses=problem_responses(*READ, 404))
async def revoke(name: Annotated[str, Path(max_length=100)], tokens: TokensRepoDep, cache: TokenCacheDep, who: Admin) -> Token:
    """Revoke a token: requests with it are refused (401) from this answer on."""
    row = await run_in_threadpool(tokens.revoke_token, name, actor=who.name)
    if cache is not None:
        cache.clear()  # the revoked token stops working now, not when its cache entry runs out
    return token_body(row)
