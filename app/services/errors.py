"""Service-level failures; ``app.main`` maps them to HTTP replies."""

from typing import TypeVar

from sqlalchemy.orm import Session

T = TypeVar("T")

#: The largest id the API takes: signed 64-bit, SQLite's integers (a larger one must not
#: reach the database driver, which raises OverflowError on it).
MAX_ID = 2**63 - 1
#: The largest id a stored row can have on every engine: id columns are 32-bit integers
#: on PostgreSQL (SQLite's ids count up from 1 and stay far below it).
MAX_ROW_ID = 2**31 - 1


class ServiceError(Exception):
    """Base of the errors a client caused; ``status_code`` is the HTTP status."""

    status_code = 400

    def __init__(self, detail: str) -> None:
        super().__init__(detail)
        self.detail = detail


class NotFound(ServiceError):
    status_code = 404


class Invalid(ServiceError):
    """Well-formed input that does not fit the stored state (e.g. a target id outside
    the environment's marker family)."""

    status_code = 422


class TooLarge(ServiceError):
    status_code = 413


class UnsupportedMedia(ServiceError):
    status_code = 415


class Conflict(ServiceError):
    status_code = 409


class NoMap(Conflict):
    """The environment exists but has no map yet: every route that needs a map answers
    this one way. 409, not 404: the environment is there and the client can resolve the
    conflict (run a survey or PUT a map) and retry, while 404 says the id itself is
    wrong; /track makes the same distinction (``unknown_environment``, ``no_map``)."""

    def __init__(self, environment_id: int) -> None:
        super().__init__(f"environment {environment_id} has no map yet: run a survey or PUT one")
        self.environment_id = environment_id

    def __reduce__(self) -> tuple[type, tuple[int]]:
        # Raised in the image worker processes too: pickled back by its argument, not its message.
        return (NoMap, (self.environment_id,))


class PreconditionFailed(ServiceError):
    """A conditional write (``If-Match``) whose condition no longer holds: it changed nothing."""

    status_code = 412


class TooMany(ServiceError):
    status_code = 429


class Busy(ServiceError):
    """The server is working at its capacity: the same request later may succeed."""

    status_code = 503


def can_match(key: object) -> bool:
    """Whether a stored row can have `key` as an id or a text key: an integer beyond
    `MAX_ROW_ID`, or text with a NUL (PostgreSQL's text cannot hold one), matches nothing
    and must not reach the database, which refuses it (an error, not an empty result)."""
    if isinstance(key, int):
        return -MAX_ROW_ID - 1 <= key <= MAX_ROW_ID
    if isinstance(key, str):
        return "\x00" not in key
    return True


def get_or_404(session: Session, model: type[T], key: object, what: str) -> T:
    """The row of ``model`` with primary key ``key``, or NotFound("<what> <key> not found")."""
    row = session.get(model, key) if can_match(key) else None
    if row is None:
        raise NotFound(f"{what} {key} not found")
    return row
