"""The service's one exception family; the HTTP layer maps each kind to a status code."""

from __future__ import annotations


class ServiceError(Exception):
    """Base of every error the service raises on purpose. `status` is the HTTP status to use."""

    status = 500

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class BadRequestError(ServiceError):
    status = 400


class UnauthorizedError(ServiceError):
    status = 401


class NotFoundError(ServiceError):
    status = 404


class ConflictError(ServiceError):
    status = 409


class PayloadTooLargeError(ServiceError):
    status = 413


class SettingsError(ServiceError):
    """Refused configuration (e.g. a non-loopback bind without a token)."""


class StoreError(ServiceError):
    """The data directory is unusable: locked by another process, unreadable, corrupt."""


class TransportError(ServiceError):
    """Zenoh could not be opened, configured or queried."""

    status = 503
