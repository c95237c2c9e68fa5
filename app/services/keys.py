"""API keys: created once (the secret is shown only then), stored as SHA-256 hashes,
verified in constant time, revoked by id.

A key reads ``ft_<prefix>_<secret>``: the prefix finds the row, the hash of the whole key
is compared with ``hmac.compare_digest``. Scopes: ``read`` (GET), ``track`` (/track,
/detect, /locate), ``admin`` (everything, including keys).
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import threading
import time
from dataclasses import dataclass, field

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from app.db import utcnow
from app.models import ApiKey
from app.services.errors import Invalid, can_match, get_or_404

SCOPES = ("read", "track", "admin")
_DUMMY_HASH = hashlib.sha256(b"no such key").hexdigest()


@dataclass(frozen=True)
class Principal:
    key_id: int
    name: str
    scopes: frozenset[str]

    def allows(self, scope: str) -> bool:
        return "admin" in self.scopes or scope in self.scopes


#: Where `ApiKeyGate` leaves a request's `Credential`, in its ASGI scope's ``state``.
CREDENTIAL_STATE = "api_key"


@dataclass(frozen=True)
class Credential:
    """A verified key as the request presented it: a /track connection checks it again
    while it is open, to close when it is revoked."""

    key: str = field(repr=False)
    principal: Principal


@dataclass(frozen=True)
class CreatedKey:
    id: int
    name: str
    scopes: list[str]
    key: str  # the secret: shown once, never stored


def _hash(key: str) -> str:
    return hashlib.sha256(key.encode("utf-8", "surrogateescape")).hexdigest()


def create(session: Session, name: str, scopes: list[str]) -> CreatedKey:
    unknown = sorted(set(scopes) - set(SCOPES))
    if unknown or not scopes:
        raise Invalid(f"scopes: give one or more of {', '.join(SCOPES)}" + (f"; unknown: {unknown}" if unknown else ""))
    if not name.strip():
        raise Invalid("name: may not be empty")
    prefix = secrets.token_hex(6)
    key = f"ft_{prefix}_{secrets.token_urlsafe(32)}"
    row = ApiKey(name=name, prefix=prefix, key_sha256=_hash(key), scopes=sorted(set(scopes)))
    session.add(row)
    session.commit()
    return CreatedKey(row.id, row.name, list(row.scopes), key)


def verify(session: Session, key: str | None) -> Principal | None:
    """The key's principal, or None for a missing, malformed, unknown or revoked key."""
    if not key or len(key) > 200:
        return None
    parts = key.split("_")
    prefix = parts[1] if len(parts) >= 3 and parts[0] == "ft" else ""
    row = session.scalar(select(ApiKey).where(ApiKey.prefix == prefix)) if prefix and can_match(prefix) else None
    # Compare even when nothing was found, so the reply time says nothing about prefixes.
    matches = hmac.compare_digest(row.key_sha256 if row is not None else _DUMMY_HASH, _hash(key))
    if row is None or not matches or row.revoked_at is not None:
        return None
    return Principal(row.id, row.name, frozenset(row.scopes))


def verify_in(sessions: sessionmaker[Session], key: str | None) -> Principal | None:
    """`verify` in a session of its own (for the gate and open connections, off the event loop)."""
    with sessions() as session:
        return verify(session, key)


#: How long a verified key is taken as valid without asking the database again, s.
VERIFIED_TTL_S = 2.0


class VerifiedKeys:
    """Principals of the keys verified in the last `ttl_s` seconds (by their hash), so
    that a client sending many requests costs a database lookup every `ttl_s`, not one
    per request. A revocation through this process clears it at once; other processes
    sharing the database refuse a revoked key within `ttl_s`."""

    def __init__(self, ttl_s: float = VERIFIED_TTL_S, max_keys: int = 10_000) -> None:
        self.ttl_s = ttl_s
        self.max_keys = max_keys
        self._lock = threading.Lock()
        self._seen: dict[str, tuple[Principal, float]] = {}

    def get(self, key: str | None) -> Principal | None:
        """The key's principal if it was verified within `ttl_s`, else None (verify it)."""
        if not key:
            return None
        with self._lock:
            found = self._seen.get(_hash(key))
        return found[0] if found is not None and found[1] > time.monotonic() else None

    def remember(self, key: str, principal: Principal) -> None:
        with self._lock:
            if len(self._seen) >= self.max_keys:
                self._seen.clear()
            self._seen[_hash(key)] = (principal, time.monotonic() + self.ttl_s)

    def clear(self) -> None:
        with self._lock:
            self._seen.clear()


def list_all(session: Session) -> list[ApiKey]:
    return list(session.scalars(select(ApiKey).order_by(ApiKey.id)))


def revoke(session: Session, key_id: int) -> ApiKey:
    row = get_or_404(session, ApiKey, key_id, "API key")
    if row.revoked_at is None:
        row.revoked_at = utcnow()
        session.commit()
    return row
