"""JSON request bodies: refuse what is not UTF-8 JSON, or nests too deep, with a clear 400.

FastAPI answers such bodies with an undocumented `400 There was an error parsing the body`
(invalid UTF-8, or a RecursionError on very deep nesting) or a 422 (bad syntax). `JsonBodyRoute`
checks the body first and raises `BadRequestError` with a code; the parsed body is cached on the
request (Starlette's `Request.json()`), so FastAPI does not parse it again. A refused body
answers the route's 401/403 first: a caller without a token learns nothing about bodies.
"""

from __future__ import annotations

import email.message
from collections.abc import Callable, Coroutine
from typing import Any, Final

from fastapi import Request, Response
from fastapi.routing import APIRoute

from service.app.api.deps import authorize
from service.app.errors import BadRequestError

MAX_JSON_DEPTH: Final = 32

_OPEN: Final = frozenset(b"[{")
_CLOSE: Final = frozenset(b"]}")
_QUOTE: Final = ord('"')
_BACKSLASH: Final = ord("\\")


def json_depth(body: bytes, limit: int = MAX_JSON_DEPTH) -> int:
    """Nesting depth of `body` (strings skipped), stopping early once above `limit`."""
    depth = deepest = 0
    in_string = escaped = False
    for byte in body:
        if in_string:
            if escaped:
                escaped = False
            elif byte == _BACKSLASH:
                escaped = True
            elif byte == _QUOTE:
                in_string = False
        elif byte == _QUOTE:
            in_string = True
        elif byte in _OPEN:
            depth += 1
            if depth > deepest:
                deepest = depth
                if deepest > limit:
                    return deepest
        elif byte in _CLOSE:
            depth -= 1
    return deepest


def _is_json(content_type: str | None) -> bool:
    if not content_type:
        return True  # FastAPI parses a body without a content type as JSON
    message = email.message.Message()
    message["content-type"] = content_type
    subtype = message.get_content_subtype()
    return message.get_content_maintype() == "application" and (
        subtype == "json" or subtype.endswith("+json")
    )


async def check_json_body(request: Request) -> None:
    """Raise `BadRequestError` unless the body is empty or UTF-8 JSON nested at most 32 deep."""
    body = await request.body()
    if not body or not _is_json(request.headers.get("content-type")):
        return
    try:
        body.decode("utf-8")
    except UnicodeDecodeError as err:
        raise BadRequestError(
            f"request body is not valid UTF-8 (byte {err.start})", code="invalid_utf8"
        ) from err
    if json_depth(body) > MAX_JSON_DEPTH:
        raise BadRequestError(
            f"request body nests deeper than {MAX_JSON_DEPTH} levels", code="json_too_deep"
        )
    try:
        await request.json()  # cached for FastAPI
    except ValueError as err:
        reason = f"request body is not valid JSON: {err}"
        raise BadRequestError(reason, code="invalid_json") from err


class JsonBodyRoute(APIRoute):
    """An API route whose JSON body is checked by `check_json_body` before FastAPI parses it."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()
        if self.body_field is None:
            return handler

        async def checked(request: Request) -> Response:
            try:
                await check_json_body(request)
            except BadRequestError:
                authorize(request, self.dependencies)  # a 401/403 comes before the body's 400
                raise
            return await handler(request)

        return checked
