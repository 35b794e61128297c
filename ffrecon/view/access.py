"""Who may talk to the viewer: its own page, opened from the URL with the token that ``ffrecon view`` prints.

viser serves its page and its WebSocket on one port (through the ``websockets`` library's
``process_request`` hook) and checks neither who asks nor from where, so any page open in the user's
browser could read the scene (a cross-origin WebSocket), and DNS rebinding reaches a loopback server under
the attacker's name. Every HTTP request and WebSocket handshake must therefore

- name this server in ``Host``: 127.0.0.1, localhost or ::1, or the ``--host`` given, with the port it
  listens on (for a wildcard host, also any IP address and this machine's own names). A rebinding page
  sends the attacker's name;
- come from this server's own page when it says where from: ``Origin``, which browsers send with every
  WebSocket handshake and cross-origin request, must be ``http://`` and such a host;
- carry the token: in the URL (``?token=...``, as printed) or in the cookie that the first page load
  with the token sets (HttpOnly, SameSite=Strict). viser's client opens its WebSocket at the page's
  address without the query, so the cookie is what lets its own page in.

Anything else gets 403. A request without ``Origin`` (curl, scripts) passes with the token alone.
"""

from __future__ import annotations

import contextlib
import hmac
import inspect
import ipaddress
import logging
import secrets
import socket
import threading
from dataclasses import dataclass
from http import HTTPStatus
from urllib.parse import parse_qs, urlsplit

logger = logging.getLogger("ffrecon.view")

LOOPBACK_NAMES = frozenset({"127.0.0.1", "localhost", "::1"})
WILDCARD_HOSTS = frozenset({"", "0.0.0.0", "::"})
_PATCH_LOCK = threading.Lock()  # one viewer at a time installs the guard (see guarded_serve)


def new_token() -> str:
    """An unguessable token for the viewer's URL (256 bits, URL-safe)."""
    return secrets.token_urlsafe(32)


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


@dataclass(frozen=True)
class AccessPolicy:
    """The checks of one viewer listening on ``host`` (as the user gave it) and ``port`` (as bound)."""

    host: str
    port: int
    token: str

    @property
    def cookie_name(self) -> str:
        """Per port: browsers share a host's cookies between its ports."""
        return f"ffrecon-view-{self.port}"

    def cookie(self) -> str:
        """The ``Set-Cookie`` value that lets the page's own follow-up requests and WebSocket in."""
        return f"{self.cookie_name}={self.token}; Path=/; HttpOnly; SameSite=Strict"

    def own_host(self, authority: str) -> bool:
        """Whether ``authority`` (``name:port`` as in a Host header) names this server."""
        if not authority or any(c in authority for c in "@/\\?# "):
            return False
        try:
            parts = urlsplit("//" + authority)
            name, port = parts.hostname, parts.port if parts.port is not None else 80
        except ValueError:
            return False
        if not name or port != self.port:
            return False
        given = self.host.strip("[]").lower()
        if given in WILDCARD_HOSTS:  # any address of this machine; a rebinding page sends a domain name
            return name in LOOPBACK_NAMES or _is_ip(name) or name in _machine_names()
        return name in LOOPBACK_NAMES or name == given

    def own_origin(self, origin: str) -> bool:
        """Whether ``origin`` (an Origin header) is this server's own page."""
        return origin.startswith("http://") and self.own_host(origin.removeprefix("http://"))

    def token_given(self, request) -> str:
        """Where ``request`` carries the right token: ``"url"``, ``"cookie"``, or ``""`` (not at all)."""
        query = parse_qs(urlsplit(request.path).query).get("token", [])
        if any(self._right(t) for t in query):
            return "url"
        for header in request.headers.get_all("Cookie"):
            for part in header.split(";"):
                name, _, value = part.strip().partition("=")
                if name == self.cookie_name and self._right(value):
                    return "cookie"
        return ""

    def refusal(self, request) -> str:
        """Why ``request`` (a ``websockets.http11.Request``) is refused; ``""`` lets it through."""
        hosts = request.headers.get_all("Host")
        if len(hosts) != 1 or not self.own_host(hosts[0]):
            return f"Host {', '.join(hosts) or '(none)'} is not this viewer"
        origins = request.headers.get_all("Origin")
        if len(origins) > 1 or (origins and not self.own_origin(origins[0])):
            return f"a page from {', '.join(origins)} may not read this viewer"
        if not self.token_given(request):
            return "no token, or a wrong one"
        return ""

    def _right(self, candidate: str) -> bool:
        return hmac.compare_digest(candidate.encode(), self.token.encode())


def _machine_names() -> set[str]:
    return {socket.gethostname().lower(), socket.getfqdn().lower()}


class Gate:
    """The guard in front of viser's request handler. Refuses everything until :meth:`open` gives it the
    policy (the port is known only once the server has bound it)."""

    def __init__(self) -> None:
        self.policy: AccessPolicy | None = None
        self.installed = False  # set when viser's server was started through the guard
        self._said: set[str] = set()  # refusals logged once (a stale tab of an earlier viewer retries forever)

    def open(self, policy: AccessPolicy) -> None:
        self.policy = policy

    def wrap(self, inner):
        """``process_request`` that checks first, then calls viser's ``inner`` (sets the cookie on the page)."""

        async def process_request(connection, request):
            policy = self.policy
            why = policy.refusal(request) if policy is not None else "the viewer is starting"
            if why:
                level = logging.DEBUG if why in self._said else logging.INFO
                if len(self._said) < 100:  # Host and Origin come from the request: bounded
                    self._said.add(why)
                logger.log(level, "viewer: refused a request for %s (%s)", urlsplit(request.path).path, why)
                text = f"403 Forbidden: {why}. Open the address `ffrecon view` printed (with its ?token=...).\n"
                return connection.respond(HTTPStatus.FORBIDDEN, text)
            response = inner(connection, request) if inner is not None else None
            if inspect.isawaitable(response):
                response = await response
            if response is not None:
                response.headers["Referrer-Policy"] = "no-referrer"  # the token stays out of Referer
                if response.status_code == HTTPStatus.OK and policy.token_given(request) == "url":
                    response.headers["Set-Cookie"] = policy.cookie()
            return response

        return process_request


@contextlib.contextmanager
def guarded_serve(gate: Gate):
    """While open, every ``websockets`` server started (viser's, in its thread) runs ``gate`` before its own
    request handler. viser offers no hook of its own; it calls ``websockets.asyncio.server.serve`` with its
    handler, so the guard wraps that call for as long as the viewer takes to start. The caller must check
    ``gate.installed`` afterwards: a viser that starts its server another way serves unguarded."""
    import websockets.asyncio.server as ws_server

    with _PATCH_LOCK:
        original = ws_server.serve

        def serve(*args, process_request=None, **kwargs):
            gate.installed = True
            return original(*args, process_request=gate.wrap(process_request), **kwargs)

        ws_server.serve = serve
        try:
            yield gate
        finally:
            ws_server.serve = original
