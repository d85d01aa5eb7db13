"""Request dependencies: the runtime and its parts, and the bearer-token check."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.app.errors import UnauthorizedError
from service.app.runtime import MappingRuntime
from service.app.sessions import SessionManager

_bearer = HTTPBearer(
    auto_error=False,
    description="Required for control operations when the service has a token.",
)


def get_runtime(request: Request) -> MappingRuntime:
    runtime: MappingRuntime = request.app.state.runtime
    return runtime


def get_sessions(runtime: Annotated[MappingRuntime, Depends(get_runtime)]) -> SessionManager:
    return runtime.sessions


def require_token(
    runtime: Annotated[MappingRuntime, Depends(get_runtime)],
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> None:
    """Control operations need `Authorization: Bearer <token>` when a token is configured."""
    expected = runtime.settings.token
    if expected is None:
        return
    if credentials is None or credentials.scheme.lower() != "bearer":
        raise UnauthorizedError("this operation needs 'Authorization: Bearer <token>'")
    if not hmac.compare_digest(credentials.credentials.encode(), expected.encode()):
        raise UnauthorizedError("wrong token")


Runtime = Annotated[MappingRuntime, Depends(get_runtime)]
Sessions = Annotated[SessionManager, Depends(get_sessions)]
Control = [Depends(require_token)]
