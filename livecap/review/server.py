"""The review web app: a small JSON + WebSocket API over a :class:`ReviewSession`, and the static page.

aiohttp serves everything from one process; the page (``static/``) is three.js bundled at build
time by ``./dev`` (livecap/review/web), so nothing is fetched from the network at run time.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
from aiohttp import WSMsgType, web

from livecap.review.session import Pin, ReviewSession

STATIC = Path(__file__).parent / "static"
log = logging.getLogger(__name__)


def _change(session: ReviewSession, c, ms: float | None = None) -> dict:
    out = {"a": c.a, "b": c.b, "weights": session.weights[c.a:c.b + 1].tolist(),
           "undo": len(session.undo_stack), "redo": len(session.redo_stack)}
    if ms is not None:
        out["server_ms"] = ms
    return out


def _pins(body: dict) -> list[Pin]:
    pins = []
    for p in body.get("pins") or []:
        goal = np.asarray(p.get("goal"), dtype=np.float64)
        if goal.shape != (3,) or not np.all(np.isfinite(goal)):
            raise ValueError(f"pin goal must be [x, y, z] in mm, not {p.get('goal')!r}")
        pins.append(Pin(goal, vertex=p.get("vertex"), marker=p.get("marker")))
    return pins


def make_app(session: ReviewSession, rig_glb: bytes) -> web.Application:
    routes = web.RouteTableDef()
    camera = _camera(session)
    skipped = {"ws": 0}  # bad WebSocket messages, counted and logged

    def bad(exc: Exception) -> web.Response:
        return web.json_response({"error": str(exc)}, status=400)

    @routes.get("/")
    async def index(request):
        page = STATIC / "index.html"
        if not (STATIC / "app.js").exists():
            return web.Response(status=503, text="the review page is not built: run ./dev (npm run build in "
                                "livecap/review/web)")
        return web.FileResponse(page)

    @routes.get("/rig.glb")
    async def rig(request):
        return web.Response(body=rig_glb, content_type="model/gltf-binary")

    @routes.get("/api/meta")
    async def meta(request):
        s = session
        return web.json_response({
            "names": s.names, "rig_names": s.rig.names, "n_frames": s.n_frames, "rate": s.take.rate,
            "first_frame": s.take.first_frame, "labels": s.profile.labels, "has_truth": s.truth is not None,
            "n_vertices": s.rig.n_vertices, "camera": camera, "lower": s.profile.lower.tolist(),
            "upper": s.profile.upper.tolist()})

    @routes.get("/api/curves")
    async def curves(request):
        s = session
        return web.json_response({"weights": s.weights.T.round(5).tolist(), "residual": s.residuals().round(4).tolist(),
                                  "truth": None if s.truth is None else s.truth.T.round(5).tolist(),
                                  "undo": len(s.undo_stack), "redo": len(s.redo_stack)})

    @routes.get("/api/frame/{i}")
    async def frame(request):
        try:
            return web.json_response(session.frame(int(request.match_info["i"])))
        except ValueError as exc:
            return bad(exc)

    @routes.post("/api/edit")
    async def edit(request):
        try:
            body = await request.json()
            k = int(body["frame"])
            a, b = body.get("range") or [k, k]
            c, sec = session.edit(k, {str(n): float(v) for n, v in body["weights"].items()}, int(a), int(b))
        except (ValueError, KeyError, TypeError, json.JSONDecodeError) as exc:
            return bad(exc)
        return web.json_response(_change(session, c, sec * 1e3))

    @routes.post("/api/undo")
    async def undo(request):
        c = session.undo()
        return web.json_response(None if c is None else _change(session, c))

    @routes.post("/api/redo")
    async def redo(request):
        c = session.redo()
        return web.json_response(None if c is None else _change(session, c))

    def pose(body: dict) -> dict:
        k = int(body["frame"])
        w, sec = session.pose(k, _pins(body))
        out = {"frame": k, "weights": w.tolist(), "server_ms": sec * 1e3}
        if body.get("commit"):
            a, b = body.get("range") or [k, k]
            c, esec = session.edit(k, dict(zip(session.names, w.tolist(), strict=True)), int(a), int(b))
            out["change"] = _change(session, c, esec * 1e3)
        return out

    @routes.post("/api/pose")
    async def pose_http(request):
        try:
            return web.json_response(pose(await request.json()))
        except (ValueError, KeyError, TypeError, json.JSONDecodeError) as exc:
            return bad(exc)

    @routes.get("/ws")
    async def ws(request):
        sock = web.WebSocketResponse()
        await sock.prepare(request)
        async for msg in sock:
            if msg.type != WSMsgType.TEXT:
                continue
            try:
                await sock.send_json(pose(json.loads(msg.data)))
            except (ValueError, KeyError, TypeError) as exc:
                skipped["ws"] += 1
                log.warning("ws: bad drag message skipped (%d so far): %s", skipped["ws"], exc)
                await sock.send_json({"error": str(exc), "skipped": skipped["ws"]})
        return sock

    @routes.get("/api/keys")
    async def keys(request):
        try:
            return web.json_response(session.keys_report(float(request.query.get("max_error", 0.01))))
        except ValueError as exc:
            return bad(exc)

    def attachment(filename: str, content_type: str, **content) -> web.Response:
        return web.Response(**content, content_type=content_type,
                            headers={"Content-Disposition": f'attachment; filename="{filename}"'})

    @routes.get("/export/weights.csv")
    async def weights_csv(request):
        return attachment("weights.csv", "text/csv", text=session.weights_csv())

    @routes.get("/export/keys.csv")
    async def keys_csv(request):
        try:
            text = session.keys_csv(float(request.query.get("max_error", 0.01)))
        except ValueError as exc:
            return bad(exc)
        return attachment("keys.csv", "text/csv", text=text)

    @routes.get("/export/keys.glb")
    async def keys_glb(request):
        try:
            body = session.keys_glb(float(request.query.get("max_error", 0.01)))
        except ValueError as exc:
            return bad(exc)
        return attachment("keys.glb", "model/gltf-binary", body=body)

    app = web.Application()
    app.add_routes(routes)
    app.router.add_static("/static", STATIC)
    return app


def _camera(session: ReviewSession) -> dict:
    """The offscreen preview's camera (viewer.scene.Camera.frame), so page and renderer frame the face alike."""
    from viewer.scene import Camera

    cam = Camera.frame(session.rig.neutral, 4 / 3)
    return {"eye": cam.eye.tolist(), "target": cam.target.tolist(), "fov_y": cam.fov_y, "near": cam.near,
            "far": cam.far}
