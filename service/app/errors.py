"""The service's one exception family; the HTTP layer maps each kind to a status code.

Every HTTP error body is `{"detail": "<one-line reason>", "code": "<machine-readable code>"}`;
`code` defaults to the kind's own and may be narrowed (e.g. `no_pose_yet` for a 404).
"""

from __future__ import annotations


class ServiceError(Exception):
    """Base of every error the service raises on purpose. `status` is the HTTP status to use."""

    status = 500
    default_code = "internal_error"

    def __init__(self, reason: str, code: str | None = None) -> None:
        super().__init__(reason)
        self.reason = reason
        self.code = code or self.default_code


class BadRequestError(ServiceError):
    status = 400
    default_code = "bad_request"


class UnauthorizedError(ServiceError):
    status = 401
    default_code = "unauthorized"


class ForbiddenError(ServiceError):
    """A valid token without the scope the operation needs (the read token on control)."""

    status = 403
    default_code = "forbidden"


class NotFoundError(ServiceError):
    status = 404
    default_code = "not_found"


class ConflictError(ServiceError):
    status = 409
    default_code = "conflict"


class PayloadTooLargeError(ServiceError):
    status = 413
    default_code = "payload_too_large"


class SettingsError(ServiceError):
    """Refused configuration (e.g. a non-loopback bind without a token)."""


class StoreError(ServiceError):
    """The data directory is unusable: locked by another process, unreadable, corrupt."""

    default_code = "store_error"


class TransportError(ServiceError):
    """Zenoh could not be opened, configured or queried."""

    status = 503
    default_code = "zenoh_unavailable"


class UnavailableError(ServiceError):
    """Not now: the resource is restoring, or the service is at a resource limit (503).
    `retry_after_s`, when known, is sent as `Retry-After`."""

    status = 503
    default_code = "unavailable"

    def __init__(
        self, reason: str, code: str | None = None, *, retry_after_s: int | None = None
    ) -> None:
        super().__init__(reason, code)
        self.retry_after_s = retry_after_s


# A replay takes seconds (docs/service.md): clients asked to come back after this.
RESTORE_RETRY_AFTER_S = 2


def restoring_error(session_id: str) -> UnavailableError:
    """503 for a session that is still being replayed after a restart."""
    return UnavailableError(
        f"session {session_id} is restoring after a restart; retry in a few seconds",
        retry_after_s=RESTORE_RETRY_AFTER_S,
    )
