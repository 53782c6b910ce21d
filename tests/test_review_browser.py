"""The review page in a real browser (Debian's chromium through chromedriver): load the demo take,
scrub, one spacetime edit and one drag; results checked through the API and the canvas pixels,
which are compared with the offscreen renderer's frame of the same weights (face silhouettes)."""

from __future__ import annotations

import shutil
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from tests.review_server import ROOT

CHROMIUM, DRIVER = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")
pytestmark = pytest.mark.skipif(not (CHROMIUM.exists() and DRIVER.exists()),
                                reason="Debian chromium + chromium-driver not installed (./dev test installs them)")


@contextmanager
def browse(server):
    """Headless chromium on ``server``'s page once it has loaded its take: (driver, server)."""
    if not (ROOT / "livecap/review/static/app.js").exists():
        pytest.fail("the review page is not built (./dev builds it: npm run build in livecap/review/web)")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    profile = tempfile.mkdtemp(prefix="livecap-chromium-")
    opts = webdriver.ChromeOptions()
    opts.binary_location = str(CHROMIUM)
    for a in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
              "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-quic",
              "--enable-unsafe-swiftshader", "--use-angle=swiftshader", f"--user-data-dir={profile}",
              "--window-size=1400,1000", "--force-device-scale-factor=1"):
        opts.add_argument(a)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(options=opts, service=Service(str(DRIVER)))
    try:
        driver.get(server.url)
        wait(driver, "return window.review && window.review.ready", what="the page to load the take")
        yield driver, server
    finally:
        driver.quit()
        shutil.rmtree(profile, ignore_errors=True)


@pytest.fixture(scope="module")
def page(review_server):
    with browse(review_server) as opened:
        yield opened


def wait(driver, script, timeout=30.0, what="the page"):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = driver.execute_script(script)
        if v:
            return v
        time.sleep(0.1)
    status = driver.find_element("id", "status").text
    raise AssertionError(f"timed out waiting for {what} (status: {status!r})")


def api(server, path):
    return server.get(path)


def face_mask(png: bytes) -> np.ndarray:
    import cv2

    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    bg = np.array([0.14, 0.12, 0.11]) * 255  # BGR of the shared background
    return np.abs(img.astype(float) - bg).max(axis=2) > 25


def offscreen_mask(weights_by_name: dict) -> np.ndarray:
    import cv2

    from livecap.core.rig import Rig
    from viewer.renderer import Renderer

    rig = Rig.load(ROOT / "recordings/demo_rig.npz")
    w = np.zeros(rig.n_shapes)
    for n, v in weights_by_name.items():
        w[rig.index(n)] = v
    r = Renderer(rig, None, (640, 480))
    try:
        img = r.render(w, show_sites=False)
    finally:
        r.release()
    return face_mask(cv2.imencode(".png", img)[1].tobytes())


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def test_scrub_edit_drag(page):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.support.ui import Select

    driver, server = page
    meta = api(server, "/api/meta")
    names = meta["names"]
    version0 = api(server, "/api/curves")["version"]  # the server is shared with the API tests
    for box in ("show-pose", "show-markers"):  # compare the bare face with the offscreen renderer's
        driver.find_element("id", box).click()

    # scrub: a click at 3/4 of the timeline shows that frame, with the server's weights
    tl = driver.find_element("id", "timeline")
    width = tl.size["width"]
    x = 40 + 0.75 * (width - 44)
    ActionChains(driver).move_to_element_with_offset(tl, int(x - width / 2), 0).click().perform()
    expect = round(0.75 * (meta["n_frames"] - 1))
    frame = wait(driver, "return window.review.current && window.review.current.frame", what="the scrub")
    assert abs(frame - expect) <= 3
    shown = driver.execute_script("return window.review.current.weights")
    served = api(server, f"/api/frame/{frame}")["weights"]
    np.testing.assert_allclose(shown, served, atol=1e-9)
    canvas = driver.find_element("id", "face")
    before_png = canvas.screenshot_as_png
    ref = offscreen_mask(dict(zip(names, served, strict=True)))
    assert iou(face_mask(before_png), ref) > 0.9

    # spacetime edit: jawOpen to 0.95 at this frame, propagated over +-20 frames
    Select(driver.find_element("id", "edit-shape")).select_by_visible_text("jawOpen")
    driver.execute_script("const s = document.getElementById('edit-value'); s.value = 0.95;"
                          "s.dispatchEvent(new Event('input'));")
    for box, v in (("edit-a", frame - 20), ("edit-b", frame + 20)):
        el = driver.find_element("id", box)
        el.clear()
        el.send_keys(str(v))
    driver.find_element("id", "edit-apply").click()
    wait(driver, "return window.review.lastEdit", what="the edit")
    curves = api(server, "/api/curves")
    j = names.index("jawOpen")
    assert curves["weights"][j][frame] == pytest.approx(0.95, abs=1e-4)
    assert curves["version"] == version0 + 1
    edited = api(server, f"/api/frame/{frame}")["weights"]
    after_edit = face_mask(canvas.screenshot_as_png)
    assert iou(after_edit, offscreen_mask(dict(zip(names, edited, strict=True)))) > 0.9
    assert after_edit.sum() > face_mask(before_png).sum()  # the open jaw shows more face

    # drag: the chin up by 60 px; the commit's weights come back through the API
    from livecap.core.rig import Rig
    from viewer.renderer import Renderer

    rig = Rig.load(ROOT / "recordings/demo_rig.npz")
    w = np.zeros(rig.n_shapes)
    w[[rig.index(n) for n in names]] = edited
    pos = rig.evaluate(w)
    front = pos[:, 2] > np.percentile(pos[:, 2], 60)
    centre = np.abs(pos[:, 0] - np.median(pos[:, 0])) < 5
    v = int(np.flatnonzero(front & centre)[np.argmin(pos[front & centre, 1])])  # the chin
    r = Renderer(rig, None, (640, 480))
    px = r.project(pos[v:v + 1])[0]
    r.release()
    ActionChains(driver).move_to_element_with_offset(canvas, int(px[0] - 320), int(px[1] - 240) - 3) \
        .click_and_hold().move_by_offset(0, -30).move_by_offset(0, -30).release().perform()
    commit = wait(driver, "return window.review.lastCommit", what="the drag")
    live = wait(driver, "return window.review.lastDrag", what="a live drag solve over the WebSocket")
    assert live["frame"] == frame and len(live["weights"]) == len(names)
    assert commit["server_ms"] < 50
    dragged = api(server, f"/api/frame/{frame}")["weights"]
    np.testing.assert_allclose(dragged, commit["weights"], atol=1e-9)
    assert dragged[j] < edited[j] - 0.05  # dragging the chin up closes the jaw
    assert api(server, "/api/curves")["version"] == version0 + 2
    wait(driver, f"return window.review.current && window.review.current.weights[{j}] === {dragged[j]!r}",
         what="the page to show the committed drag")
    assert iou(face_mask(canvas.screenshot_as_png), offscreen_mask(dict(zip(names, dragged, strict=True)))) > 0.9


def test_page_polish(page, tmp_path):
    """Issue 37 item 8: a time axis, labelled faces, the edit box inside its column, no console 404."""
    driver, server = page
    meta = api(server, "/api/meta")
    # the time axis: round steps in seconds under the curves, drawn (not background) in its band
    axis = driver.execute_script("return window.review.axis")
    duration = (meta["n_frames"] - 1) / meta["rate"]
    assert len(axis["ticks"]) >= 4 and axis["ticks"][0] == 0 and axis["ticks"][-1] <= duration + 1e-9
    assert duration - axis["ticks"][-1] < axis["step"]
    import cv2

    tl = driver.find_element("id", "timeline")
    shot = tl.screenshot_as_png
    (tmp_path / "timeline.png").write_bytes(shot)
    img = cv2.imdecode(np.frombuffer(shot, np.uint8), cv2.IMREAD_COLOR)
    band = img[int(axis["y"]) + 5:, 60:]
    assert (np.abs(band.astype(int) - band[0, 0].astype(int)).max(axis=2) > 60).sum() > 200  # tick labels
    # the two faces are labelled, each over its own face
    if not driver.find_element("id", "show-truth").is_selected():
        driver.find_element("id", "show-truth").click()
    wait(driver, "return document.getElementById('label-truth').style.display !== 'none'", what="the truth label")
    (tmp_path / "faces.png").write_bytes(driver.find_element("id", "view").screenshot_as_png)
    view = driver.find_element("id", "view").rect
    labels = {}
    for name in ("solve", "truth"):
        el = driver.find_element("id", f"label-{name}")
        assert el.is_displayed() and el.text == name
        labels[name] = el.rect["x"] + el.rect["width"] / 2 - view["x"]
        assert 0 < labels[name] < view["width"]
    assert abs(labels["solve"] - labels["truth"]) > 120
    mask = face_mask(driver.find_element("id", "face").screenshot_as_png)
    for x in labels.values():  # a face under each label
        assert mask[:, max(0, int(x) - 10):int(x) + 10].sum() > 500
    # every control of the side column stays inside it
    over = driver.execute_script("""
        const side = document.getElementById('side').getBoundingClientRect();
        return [...document.querySelectorAll('#side *')].filter((e) => e.getBoundingClientRect().width > 0)
          .map((e) => [e.id || e.tagName, e.getBoundingClientRect().right - side.right]).filter((d) => d[1] > 0.5);""")
    assert over == []
    # the favicon is served: no 404 in the console
    status = driver.execute_async_script("fetch('/favicon.ico').then((r) => arguments[0](r.status))")
    assert status == 200
    errors = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]
    assert errors == [], errors


def test_drag_a_bound_marker_and_save(page):
    """Issue 35.1: with "move markers" on, a marker's site is picked on screen and dropped on the face; the
    server binds it to the triangle under the pointer and the saved markers.json has it."""
    from selenium.webdriver.common.action_chains import ActionChains

    driver, server = page
    for box, on in (("show-markers", True), ("show-truth", False), ("move-markers", True)):
        if driver.find_element("id", box).is_selected() != on:
            driver.find_element("id", box).click()
    driver.execute_script("const f = document.getElementById('frame'); f.value = 0;"
                          "f.dispatchEvent(new Event('change'));")
    wait(driver, "return window.review.current && window.review.current.frame === 0", what="frame 0")
    meta = api(server, "/api/meta")
    before = np.array(api(server, "/api/frame/0")["sites"])
    i = meta["labels"].index(next(lab for lab in meta["labels"] if "chin" in lab.lower() or "jaw" in lab.lower()))
    x, y = driver.execute_script(f"return window.review.screenOf(window.review.current.sites[{i}])")
    canvas = driver.find_element("id", "face").rect
    cx, cy = canvas["x"] + canvas["width"] / 2, canvas["y"] + canvas["height"] / 2
    face = driver.find_element("id", "face")
    (ActionChains(driver).move_to_element_with_offset(face, int(x - cx), int(y - cy)).click_and_hold()
     .move_by_offset(6, 0).move_by_offset(6, 0).release().perform())
    moved = wait(driver, "return window.review.lastMarker", what="the marker move")
    assert moved["label"] == meta["labels"][i] and len(moved["triangle"]) == 3
    after = np.array(api(server, "/api/frame/0")["sites"])
    shift = np.linalg.norm(after - before, axis=1)
    assert shift[i] > 1.0 and np.delete(shift, i).max() < 1e-9  # mm: only that marker moved
    status, saved = server.request("/export/markers.json")
    entry = next(m for m in saved["markers"] if m["label"] == meta["labels"][i])
    assert status == 200 and entry["barycentric"] == pytest.approx(moved["barycentric"])
    driver.find_element("id", "move-markers").click()  # back to dragging the face
