"""``livecap review``'s API against a real server process: frames, edits, undo/redo, drags, keys, exports."""

from __future__ import annotations

import asyncio
import csv
import io
import subprocess
import sys

import numpy as np
import pytest

from tests.review_server import ROOT


@pytest.fixture
def server(review_server):
    return review_server


def get(server, path):
    return server.get(path)


def post(server, path, body):
    return server.request(path, body)


def test_meta_frame_and_curves(server):
    meta = get(server, "/api/meta")
    assert meta["n_frames"] == 2400 and len(meta["names"]) == 43 and meta["has_truth"]
    f = get(server, "/api/frame/100")
    assert len(f["sites"]) == len(f["observed"]) == 60 and len(f["rotation"]) == 4
    curves = get(server, "/api/curves")
    W = np.array(curves["weights"])
    assert W.shape == (43, 2400) and np.array(curves["truth"]).shape == (43, 2400)
    res = np.array(curves["residual"])
    assert res.shape == (2400,) and np.all(res >= 0) and 0 < np.median(res) < 5  # mm
    np.testing.assert_allclose(W[:, 100], f["weights"], atol=1e-5)


def test_edit_undo_redo(server):
    names = get(server, "/api/meta")["names"]
    j = names.index("jawOpen")
    before = np.array(get(server, "/api/curves")["weights"])
    status, c = post(server, "/api/edit", {"frame": 500, "weights": {"jawOpen": 0.9}, "range": [450, 549]})
    assert status == 200 and (c["a"], c["b"]) == (450, 549) and c["server_ms"] > 0
    after = np.array(get(server, "/api/curves")["weights"])
    assert after[j, 500] == pytest.approx(0.9, abs=1e-5)
    np.testing.assert_array_equal(after[:, :450], before[:, :450])
    np.testing.assert_array_equal(after[:, 550:], before[:, 550:])
    assert np.abs(after[j, 495] - before[j, 495]) > 1e-3 and np.abs(after[j, 505] - before[j, 505]) > 1e-3
    post(server, "/api/undo", {})
    np.testing.assert_array_equal(np.array(get(server, "/api/curves")["weights"]), before)
    post(server, "/api/redo", {})
    np.testing.assert_array_equal(np.array(get(server, "/api/curves")["weights"]), after)
    post(server, "/api/undo", {})


def test_bad_requests_say_what(server):
    status, r = post(server, "/api/edit", {"frame": 10, "weights": {"noSuchShape": 1.0}, "range": [0, 20]})
    assert status == 400 and "noSuchShape" in r["error"]
    status, r = post(server, "/api/edit", {"frame": 99999, "weights": {"jawOpen": 1.0}})
    assert status == 400 and "outside" in r["error"]
    status, r = post(server, "/api/pose", {"frame": 10, "pins": [{"vertex": 10**9, "goal": [0, 0, 0]}]})
    assert status == 400 and "vertex" in r["error"]


def test_drag_over_websocket_moves_the_site_towards_the_goal(server):
    import aiohttp

    meta = get(server, "/api/meta")
    f = get(server, "/api/frame/300")
    i = meta["labels"].index(meta["labels"][40])
    site = np.array(f["sites"][i])
    goal = site + np.array([0.0, -6.0, 0.0])

    async def drag():
        async with aiohttp.ClientSession() as s, s.ws_connect(f"{server.base}/ws?token={server.token}") as ws:
            await ws.send_str("{not json")
            bad = await ws.receive_json(timeout=30)
            await ws.send_json({"frame": 300, "pins": [{"marker": "noSuchMarker", "goal": [0, 0, 0]}]})
            unknown = await ws.receive_json(timeout=30)
            await ws.send_json({"frame": 300, "pins": [{"marker": meta["labels"][i], "goal": goal.tolist()}]})
            return bad, unknown, await ws.receive_json(timeout=30)

    bad, unknown, r = asyncio.run(drag())
    assert "error" in bad and "noSuchMarker" in unknown["error"] and unknown["skipped"] == bad["skipped"] + 1
    w = np.array(r["weights"])
    assert np.all(w >= np.array(meta["lower"]) - 1e-12) and np.all(w <= np.array(meta["upper"]) + 1e-12)
    assert r["server_ms"] < 50
    from livecap.core.markers import MarkerLayout
    from livecap.core.rig import Rig

    rig = Rig.load(ROOT / "recordings/demo_rig.npz")
    layout = MarkerLayout.load(ROOT / "recordings/demo_rig.markers.json", rig)
    full = np.zeros(rig.n_shapes)
    full[[rig.index(n) for n in meta["names"]]] = w
    moved = layout.marker_rig(rig).evaluate(full)[i]
    assert np.linalg.norm(moved - goal) < np.linalg.norm(site - goal) - 1.0


def test_keys_hold_the_bound_and_export(server, tmp_path):
    rep = get(server, "/api/keys?max_error=0.05")
    assert rep["worst"] <= 0.05 and all(s["error"] <= 0.05 for s in rep["shapes"].values())
    text = get(server, "/export/keys.csv?max_error=0.05").decode()
    rows = list(csv.DictReader(io.StringIO(text)))
    assert len(rows) == rep["keys"] and set(rows[0]) == {"shape", "frame", "time", "value", "in_tangent", "out_tangent"}
    import pygltflib

    data = get(server, "/export/keys.glb?max_error=0.05")
    glb = pygltflib.GLTF2.load_from_bytes(data)
    prim = glb.meshes[0].primitives[0]
    assert len(prim.targets) == 43
    sampler = glb.animations[0].samplers[0]
    assert sampler.interpolation == "CUBICSPLINE"
    n_keys = glb.accessors[sampler.input].count
    assert glb.accessors[sampler.output].count == 3 * n_keys * 43
    from tests.gltf_validator import validate

    path = tmp_path / "keys.glb"
    path.write_bytes(data)
    report = validate(path)
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"][:3]
    wcsv = get(server, "/export/weights.csv").decode().splitlines()
    assert wcsv[0].startswith("frame,time,browDownLeft") and len(wcsv) == 2401


def test_review_refuses_a_busy_port(server):
    port = server.base.rsplit(":", 1)[1]
    r = subprocess.run([sys.executable, "-m", "livecap", "review", str(ROOT / "recordings/demo_take.c3d"),
                        "--rig", str(ROOT / "recordings/demo_rig.npz"), "--port", port, "--no-browser"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 1 and f"--port {port}" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_pose_command_reaches_a_pinned_vertex(tmp_path):
    from livecap.core.rig import Rig

    rig = Rig.load(ROOT / "recordings/demo_rig.npz")
    j = rig.index("jawOpen")
    v = int(np.argmax(np.linalg.norm(rig.deltas[j], axis=1)))
    goal = rig.neutral[v] + 0.6 * rig.deltas[j][v]
    out = tmp_path / "pose.csv"
    r = subprocess.run([sys.executable, "-m", "livecap", "pose", "--rig", str(ROOT / "recordings/demo_rig.npz"),
                        "--pin", f"{v}={goal[0]},{goal[1]},{goal[2]}", "--pull", "0.01", "--out", str(out)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    w = np.array([float(line.split(",")[1]) for line in out.read_text().splitlines()[1:]])
    reached = rig.neutral[v] + np.einsum("m,mk->k", w, rig.deltas[:, v])
    assert np.linalg.norm(reached - goal) < 0.5  # mm
    bad = subprocess.run([sys.executable, "-m", "livecap", "pose", "--rig", str(ROOT / "recordings/demo_rig.npz"),
                          "--pin", "12=1,2"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 1 and "--pin '12=1,2'" in bad.stderr


def test_a_marker_moved_on_the_face_is_rebound_and_saved(tmp_path):
    """Issue 35.1: a marker dropped on a rig triangle (the face as drawn at a frame) is bound there by
    triangle + barycentric, the page's sites follow, and markers.json saves it for the next calibration.
    Its own server: the move changes the session's layout."""
    from livecap.core.markers import MarkerLayout
    from livecap.core.rig import Rig
    from tests.review_server import ReviewServer

    rig = Rig.load(ROOT / "recordings/demo_rig.npz")
    server = ReviewServer(tmp_path)
    try:
        def save(name: str) -> MarkerLayout:
            status, body, _ = server.raw("/export/markers.json", None, {"X-Livecap-Token": server.token})
            assert status == 200
            (tmp_path / name).write_bytes(body)
            return MarkerLayout.load(tmp_path / name, rig)

        before = save("before.json")
        label = before.labels[5]
        tri = rig.triangles[1234]
        corners = [int(v) for v in tri[::-1]]  # any corner order: the rig's own order is kept
        w = np.zeros(rig.n_shapes)  # the face as drawn at frame 0
        for n, x in zip(get(server, "/api/meta")["names"], get(server, "/api/frame/0")["weights"], strict=True):
            w[rig.index(n)] = x
        drawn = MarkerLayout.from_vertices(["a", "b", "c"], tri, [False] * 3).marker_rig(rig).evaluate(w)
        point = drawn.mean(axis=0) + np.array([0.0, 0.0, 0.3])
        status, r = post(server, "/api/markers", {"frame": 0, "label": label, "triangle": corners,
                                                  "point": point.tolist()})
        assert status == 200, r
        assert r["triangle"] == tri.tolist() and r["moved"] == [label]
        np.testing.assert_allclose(r["barycentric"], [1 / 3] * 3, atol=0.05)
        site = np.array(get(server, "/api/frame/0")["sites"])[before.labels.index(label)]
        assert np.linalg.norm(site - drawn.mean(axis=0)) < 1.0  # mm
        after = save("markers.json")
        i = after.labels.index(label)
        assert after.vertices[i].tolist() == tri.tolist()
        others = [j for j in range(after.n_markers) if j != i]
        np.testing.assert_array_equal(after.vertices[others], before.vertices[others])
        status, r = post(server, "/api/markers", {"frame": 0, "label": before.labels[6], "triangle": corners,
                                                  "point": point.tolist()})
        assert status == 400 and "share its site" in r["error"]  # two markers on one site is refused
    finally:
        server.close()
