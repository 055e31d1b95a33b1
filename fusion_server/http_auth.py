"""Bearer tokens for the REST API: who may read the fleet's data when the API is reachable beyond loopback.

The map page shell, its static files, the OpenAPI schema, the API docs and ``/healthz`` stay public (they hold no data);
every other path needs ``Authorization: Bearer TOKEN`` or, for map tiles in an ``<img>``, ``?access_token=``.
"""

from __future__ import annotations

import hmac
import ipaddress
import logging
import os
from collections.abc import Awaitable, Callable, Iterable, MutableMapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs

__all__ = ["PUBLIC_PATHS", "BearerAuth", "HttpToken", "is_loopback_host", "read_token_file"]

log = logging.getLogger(__name__)

#: paths served without a token: the page shell and its files, the API schema and docs, the health check
PUBLIC_PATHS = ("/", "/healthz", "/openapi.json", "/docs", "/docs/oauth2-redirect", "/redoc")
PUBLIC_PREFIXES = ("/static/", "/docs-static/")
MIN_TOKEN_LEN = 16

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
App = Callable[[Scope, Receive, Send], Awaitable[None]]


@dataclass(frozen=True, slots=True)
class HttpToken:
    """One accepted token and the name it is logged under (never the token itself)."""

    name: str
    token: str = ""

    def __post_init__(self) -> None:
        if len(self.token) < MIN_TOKEN_LEN or any(c.isspace() for c in self.token):
            raise ValueError(f"REST token {self.name!r} must be at least {MIN_TOKEN_LEN} characters without "
                             f"spaces, got {len(self.token)} characters")

    def __repr__(self) -> str:  # keep the secret out of logs and tracebacks
        return f"HttpToken(name={self.name!r}, token=...)"


def is_loopback_host(host: str) -> bool:
    """True for ``localhost`` and loopback addresses (127.0.0.0/8, ::1); False for 0.0.0.0, :: and the rest."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def read_token_file(path: Path) -> tuple[HttpToken, ...]:
    """Tokens from a file: one per line, ``TOKEN`` or ``NAME:TOKEN``; blank lines and ``#`` comments skipped.

    Raises ValueError naming the file and line for an unreadable file, a bad line or no token at all.
    """
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"cannot read the token file {path}: {exc}") from None
    tokens = []
    for number, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        name, sep, token = line.partition(":")
        if not sep:
            name, token = f"line {number}", line
        try:
            tokens.append(HttpToken(name.strip() or f"line {number}", token.strip()))
        except ValueError as exc:
            raise ValueError(f"{path}:{number}: {exc}") from None
    if not tokens:
        raise ValueError(f"the token file {path} holds no token")
    if os.name == "posix" and path.stat().st_mode & 0o077:
        log.warning("token file %s is readable by others than its owner: chmod 600 it", path)
    return tuple(tokens)


def _bearer(scope: Scope) -> str | None:
    for name, value in scope.get("headers", ()):
        if name == b"authorization":
            scheme, _, credentials = value.decode("latin-1").partition(" ")
            return credentials.strip() if scheme.lower() == "bearer" else None
    query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
    values = query.get("access_token")
    return values[-1] if values else None


class BearerAuth:
    """ASGI middleware: 401 for a protected path without a valid token (constant-time comparison)."""

    def __init__(self, app: App, tokens: Iterable[HttpToken],
                 on_denied: Callable[[str], None] | None = None) -> None:
        """on_denied: called with ``no_token`` or ``bad_token`` for every refused request (metrics)."""
        self.app = app
        self.tokens = tuple(tokens)
        if not self.tokens:
            raise ValueError("BearerAuth needs at least one token")
        self.on_denied = on_denied

    def _public(self, path: str) -> bool:
        return path in PUBLIC_PATHS or path.startswith(PUBLIC_PREFIXES)

    def _who(self, presented: str | None) -> str | None:
        if not presented:
            return None
        found = None
        for item in self.tokens:  # compare with every token: the time does not tell which one matched
            if hmac.compare_digest(presented.encode(), item.token.encode()):
                found = item.name
        return found

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or self._public(scope.get("path", "")):
            await self.app(scope, receive, send)
            return
        presented = _bearer(scope)
        who = self._who(presented)
        if who is None:
            if self.on_denied is not None:
                self.on_denied("bad_token" if presented else "no_token")
            await _unauthorized(send)
            return
        scope.setdefault("state", {})["token_name"] = who
        await self.app(scope, receive, send)


async def _unauthorized(send: Send) -> None:
    body = b'{"detail":"this API needs a bearer token: Authorization: Bearer TOKEN (see docs/fusion.md)"}'
    await send({"type": "http.response.start", "status": 401, "headers": [
        (b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
        (b"www-authenticate", b'Bearer realm="uavmm"')]})
    await send({"type": "http.response.body", "body": body})
