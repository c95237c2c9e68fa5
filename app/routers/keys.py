"""API keys (admin scope): create (the secret is in this reply only), list, revoke."""

from __future__ import annotations

from fastapi import APIRouter, status

from app.deps import RowId, SessionDep, VerifiedKeysDep
from app.routers.json_bodies import JsonBodyRoute
from app.routers.responses import invalid, not_found
from app.schemas import ApiKeyCreate, ApiKeyCreated, ApiKeyOut
from app.services import keys

router = APIRouter(prefix="/keys", tags=["keys"], route_class=JsonBodyRoute)
_422 = invalid()


@router.post("", status_code=status.HTTP_201_CREATED, response_model=ApiKeyCreated, summary="Create an API key",
             responses=_422)
def create_key(spec: ApiKeyCreate, session: SessionDep) -> ApiKeyCreated:
    """A new key with its scopes. The reply holds the secret, once: only its hash is
    stored."""
    created = keys.create(session, spec.name, list(spec.scopes))
    return ApiKeyCreated(id=created.id, name=created.name, scopes=created.scopes, key=created.key)


@router.get("", response_model=list[ApiKeyOut], summary="List the API keys")
def list_keys(session: SessionDep) -> list[ApiKeyOut]:
    """Every key, revoked ones included, without their secrets."""
    return [ApiKeyOut.model_validate(k, from_attributes=True) for k in keys.list_all(session)]


@router.delete("/{key_id}", response_model=ApiKeyOut, summary="Revoke an API key",
               responses={**not_found("key"), **_422})
def revoke_key(key_id: RowId, session: SessionDep, verified: VerifiedKeysDep) -> ApiKeyOut:
    """Revoke a key: it is refused from the next request on. The row stays, to show
    when it was revoked."""
    revoked = keys.revoke(session, key_id)
    verified.clear()  # refused from the next request on, not after the cache's few seconds
    return ApiKeyOut.model_validate(revoked, from_attributes=True)
