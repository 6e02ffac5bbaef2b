"""Who may command through the panel: a token, the panel's own origin and host, JSON commands only.

The panel moves a robot (with HIL, a real motor), and a browser sends requests to 127.0.0.1 from any
page it has open: a form or ``fetch`` with ``Content-Type: text/plain`` needs no preflight, and a
DNS-rebinding page reaches the panel under a foreign ``Host``. So, as Jupyter guards its server, every
HTTP request passes :class:`Guard` (ASGI middleware) before any route:

- **a token** (``secrets.token_urlsafe``, new for each start) unless ``--no-token``: in the URL the panel
  prints (``?token=…``), in an ``Authorization: token …`` header, or in the cookie the panel sets when its
  page is opened with the token (``HttpOnly``, ``SameSite=Strict``, named after the port), which the
  page's own requests then carry. Without it: 403;
- **the panel's own host**: a ``Host`` header other than the address it listens on (loopback: ``127.0.0.1``,
  ``localhost``, ``[::1]``, with its port) is refused (403): a DNS-rebinding page's requests carry its own
  name. Listening on every interface (``0.0.0.0``, ``::``), the host is not checked (the token is);
- **the panel's own origin**: a request whose ``Origin`` is not the panel's (scheme, host, port), or that
  the browser marks as sent from another site (``Sec-Fetch-Site`` other than ``same-origin`` or ``none``)
  is refused (403), whatever token or cookie it carries: a page on another port of the same machine is
  "same-site" to a cookie, not the same origin;
- **commands are JSON**: a ``POST`` whose ``Content-Type`` is not ``application/json`` is refused (415),
  so no HTML form can send one, and a cross-origin ``fetch`` of it needs a preflight (which is refused).

Each refusal is one line on the panel's output (``hilsim panel: refused POST /api/goal: …``) and a JSON
answer ``{"error", "field": "request"}``. No Zenoh keys.
"""

from __future__ import annotations

import json
import secrets
import sys
from collections.abc import Awaitable, Callable, MutableMapping
from http.cookies import SimpleCookie
from typing import Any
from urllib.parse import parse_qs

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
App = Callable[[Scope, Receive, Send], Awaitable[None]]

LOOPBACK = ("127.0.0.1", "localhost", "::1")
EVERY_INTERFACE = ("0.0.0.0", "::", "")
SAFE_SITES = ("same-origin", "none")  # Sec-Fetch-Site: the page itself, or typed into the address bar


def new_token() -> str:
    return secrets.token_urlsafe(32)


def cookie_name(port: int) -> str:
    """Cookies are shared by every port of a host: one name per panel."""
    return f"hilsim-panel-{port}"


def _hostport(host: str, port: int) -> str:
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


class Guard:
    """ASGI middleware in front of the panel's app (module docstring). ``token`` None: ``--no-token``."""

    def __init__(self, app: App, *, host: str, port: int, token: str | None,
                 say: Callable[[str], None] | None = None) -> None:
        self.app = app
        self.token = token
        self.port = port
        self.cookie = cookie_name(port)
        names = LOOPBACK if host in LOOPBACK else (host,)
        # None: every interface, any name the machine has (the token still guards it)
        self.hosts: set[str] | None = None if host in EVERY_INTERFACE else {_hostport(h, port) for h in names}
        self.say = say or (lambda line: print(line, file=sys.stderr, flush=True))
        self.refused = 0

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        why, status = self._why(scope, headers)
        if why is not None:
            self.refused += 1
            self.say(f"hilsim panel: refused {scope['method']} {scope['path']}: {why}")
            await self._answer(send, status, why)
            return
        set_cookie = self.token is not None and self._query_token(scope) == self.token and \
            self._cookie_token(headers) != self.token
        if not set_cookie:
            await self.app(scope, receive, send)
            return

        async def send_with_cookie(message: Message) -> None:
            if message["type"] == "http.response.start":
                # the page keeps the token: its own later requests (fetch, events, static) carry it
                value = f"{self.cookie}={self.token}; Path=/; HttpOnly; SameSite=Strict"
                message = {**message, "headers": [*message.get("headers", []), (b"set-cookie", value.encode())]}
            await send(message)

        await self.app(scope, receive, send_with_cookie)

    def _why(self, scope: Scope, headers: dict[str, str]) -> tuple[str | None, int]:
        host = headers.get("host", "")
        if self.hosts is not None and host.lower() not in self.hosts:
            return f"Host {host!r} is not this panel's ({', '.join(sorted(self.hosts))}): a DNS-rebinding page?", 403
        origin = headers.get("origin")
        if origin is not None and origin.lower() != f"http://{host.lower()}":
            return f"Origin {origin!r} is not this panel's (http://{host}): a page of another site", 403
        site = headers.get("sec-fetch-site")
        if site is not None and site not in SAFE_SITES:
            return f"sent from another site's page (Sec-Fetch-Site: {site})", 403
        if self.token is not None and not self._has_token(scope, headers):
            return "no token or a wrong one: open the URL hilsim printed (http://…/?token=…)", 403
        if scope["method"] not in ("GET", "HEAD", "OPTIONS"):
            media = headers.get("content-type", "").split(";")[0].strip().lower()
            if media != "application/json":
                return f"a command must be application/json, not {media or 'untyped'}", 415
        return None, 200

    def _query_token(self, scope: Scope) -> str | None:
        got = parse_qs(scope.get("query_string", b"").decode("latin-1")).get("token")
        return got[0] if got else None

    def _cookie_token(self, headers: dict[str, str]) -> str | None:
        jar: SimpleCookie = SimpleCookie()
        try:
            jar.load(headers.get("cookie", ""))
        except Exception:  # a malformed cookie header is no token
            return None
        m = jar.get(self.cookie)
        return m.value if m is not None else None

    def _has_token(self, scope: Scope, headers: dict[str, str]) -> bool:
        assert self.token is not None
        auth = headers.get("authorization", "")
        scheme, _, value = auth.partition(" ")
        offered = [self._query_token(scope), self._cookie_token(headers),
                   value.strip() if scheme.lower() in ("token", "bearer") else None]
        return any(t is not None and secrets.compare_digest(t, self.token) for t in offered)

    @staticmethod
    async def _answer(send: Send, status: int, why: str) -> None:
        body = json.dumps({"error": why, "field": "request"}).encode()
        await send({"type": "http.response.start", "status": status,
                    "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": body})
