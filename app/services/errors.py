"""Service-level failures; ``app.main`` maps them to HTTP replies."""

from typing import TypeVar

from sqlalchemy.orm import Session

T = TypeVar("T")

#: Database ids are signed 64-bit: a larger one matches nothing, and must not reach the
#: database driver (which raises OverflowError on it).
MAX_ID = 2**63 - 1


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


class TooMany(ServiceError):
    status_code = 429


class Busy(ServiceError):
    """The server is working at its capacity: the same request later may succeed."""

    status_code = 503


def get_or_404(session: Session, model: type[T], key: object, what: str) -> T:
    """The row of ``model`` with primary key ``key``, or NotFound("<what> <key> not found")."""
    row = None if isinstance(key, int) and not -MAX_ID - 1 <= key <= MAX_ID else session.get(model, key)
    if row is None:
        raise NotFound(f"{what} {key} not found")
    return row
