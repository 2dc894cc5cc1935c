"""`RequestGuard`: the checks every request passes before any route reads it (pure ASGI).

In order, each answering ``{"detail": ...}`` without reading the request's body:

1. **Loopback only without a token.** With no ``STREP_API_TOKEN``, a client whose address is
   not a loopback one gets 403, however the server was started (``strep serve`` refuses to
   bind off loopback; ``uvicorn --factory app.main:create_app --host 0.0.0.0`` cannot be
   refused at start, so it is refused here, per connection).
2. **Host and Origin (loopback mode).** With no token, the ``Host`` header must name this
   machine (``localhost``, ``127.0.0.1``, ``[::1]``, or a name in ``STREP_ALLOWED_HOSTS``):
   421 otherwise, which stops DNS rebinding. An ``Origin`` header, when sent (browsers send
   one on every cross-site POST and websocket), must be such a host too or one of
   ``STREP_CORS_ORIGINS``: 403 otherwise, which stops cross-site forms and scripts.
3. **The bearer token** (``/api`` only, when set): 401 before the body is read.
4. **The body size** (``/api`` only, not the streamed upload route, which has its own limit):
   a declared ``Content-Length`` over ``STREP_MAX_BODY_BYTES`` is 413 at once; a chunked body
   is read up to the limit (413 past it) and then handed to the route.
"""

from __future__ import annotations

import hmac
import ipaddress
import json
from collections.abc import Awaitable, Callable, Mapping, MutableMapping
from typing import Any
from urllib.parse import urlsplit

from app.core.config import Settings, is_loopback

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

UPLOAD_ROUTE = ("POST", "/api/sequences")  # streamed to disk with its own limit (max_upload_bytes)


class Refused(Exception):
    """A request refused before its route runs."""

    def __init__(self, status: int, detail: str, headers: dict[str, str] | None = None) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail
        self.headers = headers or {}


def host_of(authority: str) -> str:
    """The host of a ``Host`` header or URL authority, without port or IPv6 brackets, lower case."""
    text = authority.strip().lower()
    if text.startswith("["):
        return text[1 : text.find("]")] if "]" in text else text
    if text.count(":") == 1:
        return text.split(":", 1)[0]
    return text


def is_loopback_client(address: str) -> bool:
    """False only for a client with an IP address off loopback (an IPv4 one mapped into IPv6 too).

    Clients without an IP address (a Unix socket, an in-process test client) count as local.
    """
    try:
        ip = ipaddress.ip_address(address)
    except ValueError:
        return True
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    return ip.is_loopback


class LocalOnly:
    """The loopback-mode checks (1 and 2 above), shared by the API and the 3D viewer's websocket."""

    def __init__(self, settings: Settings) -> None:
        self.allowed_hosts = {h.lower() for h in settings.allowed_hosts}
        self.allowed_origins = {o.rstrip("/").lower() for o in settings.cors_origins}

    def refusal(self, client: str | None, headers: Mapping[str, str]) -> Refused | None:
        """Why a request from ``client`` with ``headers`` (lower-case names) is refused; None: accepted."""
        if client and not is_loopback_client(client):
            return Refused(
                403,
                "this service has no STREP_API_TOKEN, so it answers only on this machine; set one to serve "
                "other machines (clients then send 'Authorization: Bearer <token>')",
            )
        host = headers.get("host")
        if host is not None and not self._local_host(host_of(host)):
            return Refused(421, f"Host {host[:100]!r} is not this machine (allowed: localhost, 127.0.0.1, [::1])")
        origin = headers.get("origin")
        if origin is not None and not self._local_origin(origin):
            return Refused(403, f"cross-site request from origin {origin[:100]!r} refused")
        return None

    def _local_host(self, host: str) -> bool:
        return is_loopback(host) or host in self.allowed_hosts

    def _local_origin(self, origin: str) -> bool:
        if origin.rstrip("/").lower() in self.allowed_origins:
            return True
        try:
            parts = urlsplit(origin)
        except ValueError:
            return False
        return parts.scheme in ("http", "https", "ws", "wss") and self._local_host(host_of(parts.netloc))


class RequestGuard:
    """ASGI middleware applying the checks above (see the module docstring)."""

    def __init__(self, app: ASGIApp, settings: Settings) -> None:
        self.app = app
        self.settings = settings
        token = settings.api_token
        self.token = token.get_secret_value().encode() if token is not None else None
        # with a token, the token guards (browsers never send it by themselves) and CORS governs reads
        self.local = LocalOnly(settings) if self.token is None else None

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        headers = _headers(scope)
        try:
            if self.local is not None:
                client = scope.get("client")
                refused = self.local.refusal(str(client[0]) if client else None, headers)
                if refused is not None:
                    raise refused
            path = scope.get("path", "")
            api = path == "/api" or path.startswith("/api/")
            if api and scope["type"] == "http":
                self._check_token(headers)
                if (scope.get("method"), path.rstrip("/")) != UPLOAD_ROUTE:
                    receive = await self._bounded_body(headers, receive)
        except Refused as exc:
            await _refuse(scope, receive, send, exc)
            return
        await self.app(scope, receive, send)

    def _check_token(self, headers: dict[str, str]) -> None:
        if self.token is None:
            return
        scheme, _, given = headers.get("authorization", "").partition(" ")
        if scheme.lower() != "bearer" or not hmac.compare_digest(given.strip().encode(), self.token):
            raise Refused(401, "missing or invalid bearer token", {"WWW-Authenticate": "Bearer"})

    async def _bounded_body(self, headers: dict[str, str], receive: Receive) -> Receive:
        """Read the whole body, refusing it past the limit; a ``receive`` that replays it."""
        limit = self.settings.max_body_bytes
        too_large = Refused(413, f"the request body is larger than the limit of {limit} bytes")
        length = headers.get("content-length")
        if length is not None:
            text = length.strip()
            if not (text.isascii() and text.isdigit() and len(text) <= 19):
                raise Refused(400, "invalid Content-Length header")
            if int(text) > limit:
                raise too_large
        chunks: list[bytes] = []
        size = 0
        while True:
            message = await receive()
            if message["type"] != "http.request":  # the client went away: let the route see it
                pending: list[Message] = [message]
                return _replay(pending, receive)
            body = message.get("body", b"")
            size += len(body)
            if size > limit:
                raise too_large
            chunks.append(body)
            if not message.get("more_body", False):
                break
        return _replay([{"type": "http.request", "body": b"".join(chunks), "more_body": False}], receive)


def _replay(messages: list[Message], receive: Receive) -> Receive:
    async def replay() -> Message:
        if messages:
            return messages.pop(0)
        return await receive()

    return replay


def _headers(scope: Scope) -> dict[str, str]:
    """The request's headers (the first of each name), decoded as Latin-1."""
    out: dict[str, str] = {}
    for name, value in scope.get("headers", ()):
        out.setdefault(name.decode("latin-1").lower(), value.decode("latin-1"))
    return out


async def _refuse(scope: Scope, receive: Receive, send: Send, exc: Refused) -> None:
    if scope["type"] == "websocket":
        await receive()  # websocket.connect
        await send({"type": "websocket.close", "code": 1008, "reason": exc.detail[:120]})
        return
    body = json.dumps({"detail": exc.detail}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    headers += [(k.lower().encode(), v.encode()) for k, v in exc.headers.items()]
    if exc.status == 413:
        headers.append((b"connection", b"close"))  # the rest of the body is never read
    await send({"type": "http.response.start", "status": exc.status, "headers": headers})
    await send({"type": "http.response.body", "body": body})
