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
