"""The review web app: a small JSON + WebSocket API over a :class:`ReviewSession`, and the static page.

aiohttp serves everything from one process; the page (``static/``) is three.js bundled at build
time by ``./dev`` (livecap/review/web), so nothing is fetched from the network at run time.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

from aiohttp import WSMsgType, web

from livecap.review.guard import guard
from livecap.review.requests import BadRequest, edit_request, marker_request, parse, pose_request
from livecap.review.session import EditConflict, ReviewSession

STATIC = Path(__file__).parent / "static"
FAVICON = (b'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 16 16"><circle cx="8" cy="8" r="7" '
           b'fill="#d9a68c"/></svg>')
log = logging.getLogger(__name__)


def _dumps(obj) -> str:
    return json.dumps(obj, allow_nan=False)  # strict JSON out: a NaN is a bug, not a value to send


def _json(obj, status: int = 200) -> web.Response:
    return web.json_response(obj, status=status, dumps=_dumps)


def _change(session: ReviewSession, c, client: str, ms: float | None = None) -> dict:
    undo, redo = session.depth(client)
    out = {"a": c.a, "b": c.b, "weights": session.weights[c.a:c.b + 1].tolist(), "undo": undo, "redo": redo}
    if ms is not None:
        out["server_ms"] = ms
    return out


def _client(request: web.Request) -> str:
    """The browser tab (its own undo/redo history): a short id the page keeps in sessionStorage."""
    c = request.headers.get("X-Livecap-Client") or request.query.get("client") or ""
    if len(c) > 64 or not c.replace("-", "").isalnum():
        return ""
    return c


def make_app(session: ReviewSession, rig_glb: bytes, token: str, hosts: set[str]) -> web.Application:
    """The app. ``token`` is the session's secret (docs/review.md: what the server trusts); ``hosts`` the
    ``host:port`` names the page may be reached by (the bound address and this machine's loopback names)."""
    routes = web.RouteTableDef()
    camera = _camera(session)
    skipped = {"ws": 0}  # bad WebSocket messages, counted and logged

    def bad(exc: Exception) -> web.Response:
        return _json({"error": str(exc)}, status=409 if isinstance(exc, EditConflict) else 400)

    @routes.get("/")
    async def index(request):
        if not (STATIC / "app.js").exists():
            return web.Response(status=503, text="the review page is not built: run ./dev (npm run build in "
                                "livecap/review/web)")
        page = (STATIC / "index.html").read_text().replace('content="LIVECAP_TOKEN"', f'content="{token}"')
        return web.Response(text=page, content_type="text/html",
                            headers={"Cache-Control": "no-store", "Referrer-Policy": "no-referrer"})

    @routes.get("/favicon.ico")
    async def favicon(request):
        return web.Response(body=FAVICON, content_type="image/svg+xml")

    @routes.get("/rig.glb")
    async def rig(request):
        return web.Response(body=rig_glb, content_type="model/gltf-binary")

    @routes.get("/api/meta")
    async def meta(request):
        s = session
        return _json({
            "names": s.names, "rig_names": s.rig.names, "n_frames": s.n_frames, "rate": s.take.rate,
            "first_frame": s.take.first_frame, "labels": s.profile.labels, "has_truth": s.truth is not None,
            "n_vertices": s.rig.n_vertices, "camera": camera, "lower": s.profile.lower.tolist(),
            "upper": s.profile.upper.tolist()})

    @routes.get("/api/curves")
    async def curves(request):
        s = session
        undo, redo = s.depth(_client(request))
        return _json({"weights": s.weights.T.round(5).tolist(), "residual": s.residuals().round(4).tolist(),
                      "truth": None if s.truth is None else s.truth.T.round(5).tolist(),
                      "undo": undo, "redo": redo, "version": s.version})

    @routes.get("/api/frame/{i}")
    async def frame(request):
        try:
            return _json(session.frame(int(request.match_info["i"])))
        except ValueError as exc:
            return bad(exc)

    async def body(request: web.Request) -> object:
        return parse(await request.text())

    @routes.post("/api/edit")
    async def edit(request):
        try:
            k, values, a, b = edit_request(await body(request), session)
            client = _client(request)
            c, sec = session.edit(k, values, a, b, client)
        except ValueError as exc:
            return bad(exc)
        return _json(_change(session, c, client, sec * 1e3))

    for op in ("undo", "redo"):
        async def move(request, op=op):
            client = _client(request)
            try:
                c = getattr(session, op)(client)
            except ValueError as exc:
                return bad(exc)
            return _json(None if c is None else _change(session, c, client))
        routes.post(f"/api/{op}")(move)

    def pose(data: object, client: str) -> dict:
        k, pins, commit, a, b = pose_request(data, session)
        w, sec = session.pose(k, pins)
        out = {"frame": k, "weights": w.tolist(), "server_ms": sec * 1e3}
        if commit:
            c, esec = session.edit(k, dict(zip(session.names, w.tolist(), strict=True)), a, b, client)
            out["change"] = _change(session, c, client, esec * 1e3)
        return out

    @routes.post("/api/pose")
    async def pose_http(request):
        try:
            return _json(pose(await body(request), _client(request)))
        except ValueError as exc:
            return bad(exc)

    @routes.post("/api/markers")
    async def markers(request):
        try:
            k, label, corners, point = marker_request(await body(request), session)
            return _json({**session.move_marker(k, label, corners, point), "moved": sorted(session.moved_markers)})
        except ValueError as exc:
            return bad(exc)

    @routes.get("/export/markers.json")
    async def markers_json(request):
        return attachment("markers.json", "application/json", text=session.layout.to_json(session.rig))

    @routes.get("/ws")
    async def ws(request):
        sock = web.WebSocketResponse(max_msg_size=1 << 20)
        await sock.prepare(request)
        client = _client(request)
        async for msg in sock:
            if msg.type != WSMsgType.TEXT:
                continue
            try:
                await sock.send_json(pose(parse(msg.data), client), dumps=_dumps)
            except ValueError as exc:
                skipped["ws"] += 1
                log.warning("ws: bad drag message skipped (%d so far): %s", skipped["ws"], exc)
                await sock.send_json({"error": str(exc), "skipped": skipped["ws"]}, dumps=_dumps)
        return sock

    def max_error(request) -> float:
        try:
            e = float(request.query.get("max_error", 0.01))
        except ValueError:
            raise BadRequest(f"max_error: must be a number, not {request.query.get('max_error')!r}") from None
        if not (math.isfinite(e) and 0 < e <= 1):
            raise BadRequest(f"max_error: must be in (0, 1], not {e}")
        return e

    @routes.get("/api/keys")
    async def keys(request):
        try:
            return _json(session.keys_report(max_error(request)))
        except ValueError as exc:
            return bad(exc)

    def attachment(filename: str, content_type: str, **content) -> web.Response:
        return web.Response(**content, content_type=content_type,
                            headers={"Content-Disposition": f'attachment; filename="{filename}"'})

    @routes.get("/export/weights.csv")
    async def weights_csv(request):
        return attachment("weights.csv", "text/csv", text=session.weights_csv())

    def keyed_export(filename: str, content_type: str, make):
        """An export of the key-reduced curves at the request's ``max_error``: text or bytes from ``make``."""
        async def export(request):
            try:
                data = make(max_error(request))
            except ValueError as exc:
                return bad(exc)
            return attachment(filename, content_type, **{"text" if isinstance(data, str) else "body": data})
        return export

    for filename, content_type, make in (("keys.csv", "text/csv", session.keys_csv),
                                         ("keys.glb", "model/gltf-binary", session.keys_glb),
                                         ("keys-linear.glb", "model/gltf-binary", session.linear_keys_glb)):
        routes.get(f"/export/{filename}")(keyed_export(filename, content_type, make))

    app = web.Application(middlewares=[guard(token, hosts)], client_max_size=4 << 20)
    app.add_routes(routes)
    app.router.add_static("/static", STATIC)
    return app


def _camera(session: ReviewSession) -> dict:
    """The offscreen preview's camera (viewer.scene.Camera.frame), so page and renderer frame the face alike."""
    from viewer.scene import Camera

    cam = Camera.frame(session.rig.neutral, 4 / 3)
    return {"eye": cam.eye.tolist(), "target": cam.target.tolist(), "fov_y": cam.fov_y, "near": cam.near,
            "far": cam.far}
