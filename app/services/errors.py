"""Service-level failures; ``app.main`` maps them to HTTP replies."""


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
