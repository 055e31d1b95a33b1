"""Empty optional query parameters mean "not given": a FastAPI route class for the REST API.

DESIGN.md 7 writes its URLs as ``/v1/objects?cls=&bbox=&min_score=``; clients that fill such a template
send the unused parameters empty. FastAPI would read ``min_score=`` as a malformed number (422).
"""

from __future__ import annotations

from collections.abc import Callable, Coroutine
from typing import Any
from urllib.parse import unquote_plus

from fastapi.dependencies.models import Dependant
from fastapi.routing import APIRoute
from starlette.requests import Request
from starlette.responses import Response

__all__ = ["EmptyMeansDefaultRoute", "drop_empty"]


def _optional_query_names(dependant: Dependant) -> frozenset[str]:
    """The names (aliases) of the optional query parameters of ``dependant`` and its dependencies."""
    names = {field.alias for field in dependant.query_params if not field.field_info.is_required()}
    for sub in dependant.dependencies:
        names |= _optional_query_names(sub)
    return frozenset(names)


def drop_empty(query_string: bytes, names: frozenset[str]) -> bytes:
    """``query_string`` without the pairs whose name is in ``names`` and whose value is empty.

    ``a=`` is empty; every other pair is kept byte for byte, in order (so a repeated parameter keeps its
    non-empty values, and a bare ``a``, which a client may mean as a true flag, still reaches the validation).
    Names are compared percent-decoded, as Starlette reads them.
    """
    if not query_string or not names:
        return query_string
    kept = []
    for pair in query_string.split(b"&"):
        name, equals, value = pair.partition(b"=")
        if equals and not value and unquote_plus(name.decode("latin-1")) in names:
            continue
        kept.append(pair)
    return b"&".join(kept)


class EmptyMeansDefaultRoute(APIRoute):
    """An APIRoute whose optional query parameters, when given empty (``?bbox=``), take their default.

    Required parameters are left as they came: an empty one reaches the endpoint, which says what is
    wrong with it (a 400 naming it). Non-empty values are validated as before.
    """

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()
        optional = _optional_query_names(self.dependant)

        async def route_handler(request: Request) -> Response:
            query = request.scope.get("query_string", b"")
            cleaned = drop_empty(query, optional)
            if cleaned != query:
                # a new Request: Starlette caches the parsed query parameters on the first read
                request = Request({**request.scope, "query_string": cleaned}, request.receive)
            return await handler(request)

        return route_handler
