"""Who may use the review server: checked on every request before any handler runs.

A web page the user happens to visit can make the browser send requests to 127.0.0.1 (simple
cross-origin POSTs, WebSockets, and reads after DNS rebinding), so the loopback address alone
proves nothing. Three checks, as Jupyter does (docs/review.md):

- ``Host`` must name this server (the bound address or a loopback name, with its port): a
  rebound ``attacker.example`` is refused, so a foreign page can never read a response.
- ``Origin``, when a browser sends one, must be this server's own.
- the session's secret token: from the URL the CLI printed (``?token=``, once; then a cookie
  scoped to this port), the ``X-Livecap-Token`` header the page sends, or the cookie.

State-changing requests must also be ``application/json`` (a form or ``text/plain`` body is
what a foreign page can send without a CORS preflight).
"""

from __future__ import annotations

import hmac

from aiohttp import web

OPEN = ("/favicon.ico", "/static/")  # no session data: the bundle and the icon


def allowed_hosts(bound: str, port: int, extra: tuple[str, ...] = ()) -> set[str]:
    """The ``Host`` values that name this server: loopback names and the bound address, with the port."""
    names = {"localhost", "127.0.0.1", "::1", *extra}
    if bound not in ("0.0.0.0", "::", ""):
        names.add(bound)
    return {f"[{n.lower()}]:{port}" if ":" in n else f"{n.lower()}:{port}" for n in names}


def cookie_name(hosts: set[str]) -> str:
    return "livecap-review-" + next(iter(hosts)).rsplit(":", 1)[1]  # cookies ignore ports: name it by one


def _refuse(request: web.Request, status: int, why: str) -> web.Response:
    if request.path.startswith(("/api/", "/ws")):
        return web.json_response({"error": why}, status=status)
    return web.Response(status=status, text=f"livecap review: {why}\n")


def guard(token: str, hosts: set[str]):
    origins = {f"http://{h}" for h in hosts}
    cookie = cookie_name(hosts)

    @web.middleware
    async def check(request: web.Request, handler):
        host = request.headers.get("Host", "").lower()
        if host not in hosts:
            return _refuse(request, 403, f"Host {host[:60]!r} is not this server")
        origin = request.headers.get("Origin")
        if origin is not None and origin.lower() not in origins:
            return _refuse(request, 403, f"Origin {origin[:60]!r} may not use this server")
        from_url = request.query.get("token")
        if not request.path.startswith(OPEN):
            given = from_url or request.headers.get("X-Livecap-Token") or request.cookies.get(cookie) or ""
            if not hmac.compare_digest(given.encode(), token.encode()):
                return _refuse(request, 403, "missing or wrong token: open the URL `livecap review` printed")
        if request.method == "POST" and request.content_type != "application/json":
            return _refuse(request, 415, f"Content-Type: must be application/json, not {request.content_type!r}")
        response = await handler(request)
        if from_url and not response.prepared:
            response.set_cookie(cookie, token, httponly=True, samesite="Strict", path="/")
        return response

    return check
