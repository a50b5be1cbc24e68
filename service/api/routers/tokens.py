"""API tokens over HTTP (admin): make one for a LIMS or a colleague without a shell on the daemon's
host, list them, revoke one. A token's text is answered once, by POST, and kept nowhere (only its
SHA-256); a token may name the person it belongs to (name and function: certificates state who
authorised and who ran a calibration). Each change is audited as `token.create` / `token.person` /
`token.revoke` with the admin's token name."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Query
from fastapi.responses import Response

from service.api.auth import Admin
from service.api.deps import TokenCacheDep, TokensRepoDep
from service.api.models.paging import CURSOR, DEFAULT_PAGE, LIMIT, MAX_PAGE, json_answer
from service.api.models.problem import READ, WRITE, problem_responses
from service.api.models.tokens import CreatedToken, NewToken, Person, Token, TokenPersonIn, Tokens
from service.api.offloop import in_thread
from service.api.problems import ProblemError
from service.errors import InputError
from service.jobs.requests import DB_ID_MAX
from service.storage.errors import ConflictError
from service.storage.models import ApiToken
from service.storage.store.tokens import person_of_row
from service.storage.tokens import person_of

router = APIRouter(prefix="/tokens", tags=["tokens"])


def token_body(row: ApiToken) -> Token:
    person = person_of_row(row)
    return Token(
        name=row.name,
        scopes=list(row.scopes),
        created_utc=row.created_at,
        created_by=row.created_by,
        revoked_utc=row.revoked_at,
        person=Person(name=person.name, function=person.function) if person is not None else None,
    )


@router.post(
    "", status_code=201, response_model=CreatedToken, responses=problem_responses(*WRITE, 409)
)
async def create(
    body: NewToken, response: Response, tokens: TokensRepoDep, who: Admin
) -> CreatedToken:
    """A new token; its text is in this answer only (store it now: it cannot be shown again)."""
    try:
        person = (
            person_of(body.person.model_dump(exclude_none=True))
            if body.person is not None
            else None
        )
        row, token = await in_thread(
            tokens.create_token, body.name, body.scopes, actor=who.name, person=person
        )
    except ConflictError as exc:
        raise ProblemError(409, "Token name taken", f"name: {exc}", field="name") from None
    except InputError as exc:
        field = next(
            (
                prefix
                for prefix in ("scopes", "person.name", "person.function")
                if str(exc).startswith(prefix)
            ),
            "name",
        )
        raise ProblemError(422, "Unusable token", str(exc), field=field) from None
    response.headers["Location"] = f"/tokens/{row.name}"
    response.headers["Cache-Control"] = "no-store"
    return CreatedToken(**token_body(row).model_dump(), token=token)


@router.get("", response_model=Tokens, responses=problem_responses(*READ))
async def list_tokens(
    tokens: TokensRepoDep,
    _: Admin,
    include_revoked: Annotated[bool, Query(description="list revoked tokens too")] = False,
    cursor: Annotated[int | None, Query(ge=1, le=DB_ID_MAX, description=CURSOR)] = None,
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE, description=LIMIT)] = DEFAULT_PAGE,
) -> Response:
    """Every token's name, scopes, creation and revocation, never a token's text; in the order they
    were made, a page at a time (`next_cursor` pages on)."""
    rows = await in_thread(
        tokens.page, include_revoked=include_revoked, after_id=cursor, limit=limit
    )
    return json_answer(
        Tokens(
            tokens=[token_body(row) for row in rows],
            next_cursor=rows[-1].id if len(rows) == limit else None,
        )
    )


@router.patch("/{name}", response_model=Token, responses=problem_responses(*WRITE, 404))
async def set_person(
    name: Annotated[str, Path(max_length=100)],
    body: TokenPersonIn,
    tokens: TokensRepoDep,
    cache: TokenCacheDep,
    who: Admin,
) -> Token:
    """Name the person an active token belongs to (or correct it): approvals made with it from now
    on are signed by that person. Audited as `token.person` with the person before."""
    try:
        person = person_of(body.person.model_dump(exclude_none=True))
    except InputError as exc:
        raise ProblemError(422, "Unusable person", str(exc), field=str(exc).split(":")[0]) from None
    row = await in_thread(tokens.set_person, name, person, actor=who.name)
    if cache is not None:
        cache.clear()  # requests with the token carry its new person from this answer on
    return token_body(row)


@router.delete("/{name}", response_model=Token, responses=problem_responses(*WRITE, 404, 409))
async def revoke(
    name: Annotated[str, Path(max_length=100)],
    tokens: TokensRepoDep,
    cache: TokenCacheDep,
    who: Admin,
) -> Token:
    """Revoke a token: requests with it are refused (401) from this answer on. The last admin token
    cannot be revoked (409): the lab would be locked out of its own daemon."""
    try:
        row = await in_thread(tokens.revoke_token, name, actor=who.name)
    except ConflictError as exc:
        raise ProblemError(409, "Last admin token", str(exc), field="name") from None
    if cache is not None:
        cache.clear()  # the revoked token stops working now, not when its cache entry runs out
    return token_body(row)
