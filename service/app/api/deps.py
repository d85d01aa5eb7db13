"""Request dependencies: the runtime and its parts, and the two token scopes.

- control token (`--token`): create, stop, reset, save, delete, and every read;
- read token (`--read-token`): every read (sessions, poses, trajectories, maps, the pose
  stream, /metrics, the full /health); when it is configured, reads without a token are 401.

Tokens come in `Authorization: Bearer <token>`. The pose stream alone also takes
`?access_token=<token>` (RFC 6750 §2.3), because a browser's `EventSource` cannot set headers.
"""

from __future__ import annotations

import hmac
from collections.abc import Sequence
from enum import Enum
from typing import Annotated

from fastapi import Depends, Query, Request, params
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from fastapi.security.utils import get_authorization_scheme_param

from service.app.errors import ForbiddenError, UnauthorizedError
from service.app.runtime import MappingRuntime
from service.app.sessions import SessionManager

_bearer = HTTPBearer(
    auto_error=False,
    description="The control token for control operations; the read token or the control "
    "token for reads when the service has a read token.",
)


class Scope(Enum):
    NONE = "none"  # no token presented
    WRONG = "wrong"  # a token that is neither
    READ = "read"
    CONTROL = "control"


def get_runtime(request: Request) -> MappingRuntime:
    runtime: MappingRuntime = request.app.state.runtime
    return runtime


def get_sessions(runtime: Annotated[MappingRuntime, Depends(get_runtime)]) -> SessionManager:
    return runtime.sessions


def _same(presented: str, expected: str | None) -> bool:
    if expected is None:
        return False
    # Constant-time; encode() because compare_digest refuses non-ASCII str.
    return hmac.compare_digest(presented.encode(), expected.encode())


def scope_of(runtime: MappingRuntime, token: str | None) -> Scope:
    """Which scope `token` grants (both comparisons always run: no timing hint)."""
    if token is None:
        return Scope.NONE
    control = _same(token, runtime.settings.token)
    read = _same(token, runtime.settings.read_token)
    if control:
        return Scope.CONTROL
    return Scope.READ if read else Scope.WRONG


def _bearer_token(credentials: HTTPAuthorizationCredentials | None) -> str | None:
    if credentials is None or credentials.scheme.lower() != "bearer":
        return None
    return credentials.credentials


def request_scope(
    runtime: Annotated[MappingRuntime, Depends(get_runtime)],
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> Scope:
    return scope_of(runtime, _bearer_token(credentials))


def _check_read(runtime: MappingRuntime, scope: Scope) -> None:
    if runtime.settings.read_token is None:
        return  # reads are open (loopback, or --public-reads)
    if scope is Scope.NONE:
        raise UnauthorizedError("reading needs 'Authorization: Bearer <read or control token>'")
    if scope is Scope.WRONG:
        raise UnauthorizedError("wrong token")


def require_read(
    runtime: Annotated[MappingRuntime, Depends(get_runtime)],
    scope: Annotated[Scope, Depends(request_scope)],
) -> None:
    """Reads need the read or the control token when a read token is configured."""
    _check_read(runtime, scope)


def require_read_or_query(
    runtime: Annotated[MappingRuntime, Depends(get_runtime)],
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
    access_token: Annotated[
        str | None,
        Query(
            max_length=256,
            description="the read token, for clients that cannot set headers (a browser's "
            "EventSource); the Authorization header is preferred, since URLs end up in logs",
        ),
    ] = None,
) -> None:
    """Like `require_read`, but the token may also come as `?access_token=` (header first)."""
    token = _bearer_token(credentials)
    _check_read(runtime, scope_of(runtime, token if token is not None else access_token))


def require_token(
    runtime: Annotated[MappingRuntime, Depends(get_runtime)],
    scope: Annotated[Scope, Depends(request_scope)],
) -> None:
    """Control operations need `Authorization: Bearer <control token>` when one is configured."""
    _check_control(runtime, scope)


def _check_control(runtime: MappingRuntime, scope: Scope) -> None:
    if runtime.settings.token is None:
        return
    if scope is Scope.CONTROL:
        return
    if scope is Scope.READ:
        raise ForbiddenError("the read token cannot control sessions: use the control token")
    if scope is Scope.NONE:
        raise UnauthorizedError("this operation needs 'Authorization: Bearer <token>'")
    raise UnauthorizedError("wrong token")


def authorize(request: Request, dependencies: Sequence[params.Depends]) -> None:
    """Run the token checks among a route's `dependencies` on `request` by hand: for a body
    refused before FastAPI runs them, so that a caller without a token learns 401, not 400."""
    runtime = get_runtime(request)
    scheme, token = get_authorization_scheme_param(request.headers.get("Authorization"))
    scope = scope_of(runtime, token if scheme.lower() == "bearer" and token else None)
    for dep in dependencies:
        if dep.dependency is require_token:
            _check_control(runtime, scope)
        elif dep.dependency is require_read:
            _check_read(runtime, scope)


Runtime = Annotated[MappingRuntime, Depends(get_runtime)]
Sessions = Annotated[SessionManager, Depends(get_sessions)]
RequestScope = Annotated[Scope, Depends(request_scope)]
Control = [Depends(require_token)]
Read = [Depends(require_read)]
ReadOrQuery = [Depends(require_read_or_query)]
