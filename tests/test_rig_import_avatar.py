"""The user's avatar end to end (issue 37): a VRM 0.x of the whole ICT rig (pygltflib, tests/rig_writers.py)
is the rig of ``livecap solve`` and of a live session sending VMC (decoded by python-osc); the solve goes
back into the same .vrm as an animation that the Khronos validator accepts and three.js plays."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import ICT
from tests.gltf_validator import TOOL, validate
from tests.rig_writers import perfect_sync_names, read_obj_rig, write_gltf
from tests.test_receivers import OscReceiver, check_vmc_spec
from transport.rig_files import import_rig
from transport.weights_csv import read_weights_csv


def livecap(*args, timeout: float = 180) -> subprocess.CompletedProcess:
    done = subprocess.run([sys.executable, "-m", "livecap", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)
    assert done.returncode == 0, done.stderr
    return done


@pytest.fixture(scope="module")
def avatar(ict, tmp_path_factory):
    """avatar.vrm (VRM 0.x, all 53 ICT shapes, Perfect Sync clips) with avatar.markers.json beside it, and a
    2.5 s take (livecap.demo.performance) of an actor at rest for 1 s, then opening the jaw to 0.8 while
    smiling and blinking, as C3D."""
    from livecap.demo.performance import PerformanceSettings, perform
    from transport.c3d import write_c3d

    rig, layout = ict
    d = tmp_path_factory.mktemp("avatar")
    vrm = write_gltf(d / "avatar.vrm", read_obj_rig(ICT, None, 0.01), vrm=0, sparse=True)
    shutil.copy(ICT / "markers.json", d / "avatar.markers.json")
    t = np.arange(300) / 120.0
    act = np.clip(np.sin(np.pi * (t - 1.0) / 1.5), 0, None) * (t > 1.0)
    weights = np.zeros((len(t), rig.n_shapes))
    weights[:, rig.index("jawOpen")] = 0.8 * act
    weights[:, rig.index("mouthSmile_L")] = 0.6 * act
    weights[:, rig.index("eyeBlink_R")] = act ** 4
    perf = perform(rig, layout, PerformanceSettings(seed=3, occlusion=0.0, stable_dropout=0.0), weights)
    write_c3d(perf.take, d / "take.c3d")
    return vrm, d / "take.c3d", perf


def test_solve_on_the_vrm_and_write_it_back_as_an_animation(avatar, tmp_path):
    vrm, take, perf = avatar
    livecap("solve", take, "--rig", vrm, "--out", tmp_path / "w.csv")
    names, weights, times = read_weights_csv(tmp_path / "w.csv")
    assert names == perf.names
    livecap("solve", take, "--rig", ICT, "--out", tmp_path / "obj.csv")
    _, from_obj, _ = read_weights_csv(tmp_path / "obj.csv")
    assert np.abs(weights - from_obj).max() < 1e-3  # the VRM is the OBJ folder's rig
    jaw = names.index("jawOpen")
    assert np.sqrt(np.mean((weights[:, jaw] - perf.weights[:, jaw]) ** 2)) < 0.05

    out = tmp_path / "avatar_take.vrm"
    livecap("rig", "animate", vrm, "--weights", tmp_path / "w.csv", "--out", out)
    report = validate(out)
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"][:5]
    assert [m for m in report["issues"]["messages"] if m["severity"] == 1 and "ANIMATION" in m["code"]] == []
    again = import_rig(out)  # the user's file is intact: same rig, same VRM expression table
    assert again.rig.names == names and again.expressions == import_rig(vrm).expressions
    assert json.loads(_gltf_json(out))["extensions"]["VRM"]["blendShapeMaster"]

    node = shutil.which("node")
    if node is None or not (TOOL / "node_modules" / "three").is_dir():
        pytest.skip(f"three.js not installed (run ./dev: needs node and npm install in {TOOL})")
    at = [float(times[40]), float((times[100] + times[101]) / 2)]
    played = json.loads(subprocess.run([node, str(TOOL / "three_play.mjs"), str(out), *map(str, at)],
                                       capture_output=True, text=True, timeout=120, check=True).stdout)
    assert played["tracks"] == ["FaceNode.morphTargetInfluences"]
    assert played["meshes"]["FaceNode"]["targets"] == names
    assert played["frames"][0]["FaceNode"] == pytest.approx(weights[40], abs=1e-6)
    assert played["frames"][1]["FaceNode"] == pytest.approx((weights[100] + weights[101]) / 2, abs=1e-6)
    assert played["frames"][0]["TeethNode"] == [0.0]


def _gltf_json(path: Path) -> str:
    data = path.read_bytes()
    length = int.from_bytes(data[12:16], "little")
    return data[20:20 + length].decode()


def test_a_live_session_on_the_vrm_sends_its_perfect_sync_clips_over_vmc(avatar):
    """``livecap run --rig avatar.vrm --vmc``: every Perfect Sync clip the avatar has gets a value each
    frame (python-osc decodes the bundles), and the jaw moves as the take's does."""
    vrm, take, perf = avatar
    clips = set(perfect_sync_names(perf.names))
    rx = OscReceiver()
    try:
        livecap("run", "--replay", take, "--rig", vrm, "--vmc", f"127.0.0.1:{rx.port}", "--vmc-perfect-sync",
                "--speed", 2)
    finally:
        rx.close()
    check_vmc_spec(rx.messages)
    values = [args for addr, args in rx.messages if addr == "/VMC/Ext/Blend/Val"]
    assert clips <= {name for name, _ in values}
    jaw = np.array([v for name, v in values if name == "JawOpen"])
    assert len(jaw) == len(perf.weights) and jaw.max() > 0.6 and jaw[:100].max() < 0.1


def test_markers_for_an_avatar_without_any_come_from_rig_transfer(tmp_path):
    """``livecap rig transfer --target avatar.vrm``: the generic's marker sites bound to the VRM's own vertices
    (the MakeHuman head, which has no markers.json), read by ``livecap info`` beside the .vrm."""
    from tests.test_rig_import import MAKEHUMAN, _folder

    vrm = write_gltf(tmp_path / "head.vrm", read_obj_rig(_folder(MAKEHUMAN), None, 0.01), vrm=1)
    demo = Path(__file__).resolve().parents[1] / "recordings" / "demo_rig.npz"
    livecap("rig", "transfer", "--generic", demo, "--target", vrm, "--out", tmp_path / "t", "--sheet", "none",
            "--warp", "none")
    shutil.copy(tmp_path / "t" / "markers.json", tmp_path / "head.markers.json")
    info = livecap("info", vrm).stdout
    assert "4260 vertices" in info and "markers: 60 (6 stable" in info


def test_a_rig_named_by_the_vrms_expressions_sends_its_clips_over_vmc_and_animates_it(avatar, tmp_path):
    """``rig import --names expressions`` then plain ``--vmc``: the names sent are the avatar's clips (where one
    clip drives a shape alone) and the solve's CSV, named so, animates the .vrm's targets."""
    vrm, take, perf = avatar
    rig = tmp_path / "avatar.npz"
    livecap("rig", "import", vrm, "--names", "expressions", "--out", rig, "--markers", ICT / "markers.json")
    rx = OscReceiver()
    try:
        livecap("run", "--replay", take, "--rig", rig, "--vmc", f"127.0.0.1:{rx.port}", "--speed", 2)
    finally:
        rx.close()
    check_vmc_spec(rx.messages)
    groups = json.loads(_gltf_json(vrm))["extensions"]["VRM"]["blendShapeMaster"]["blendShapeGroups"]
    clips = {g["name"] for g in groups}
    sent = {args[0] for addr, args in rx.messages if addr == "/VMC/Ext/Blend/Val"}
    assert sent & clips == set(perfect_sync_names(perf.names))
    assert sent - clips <= set(perf.names)  # shapes no clip drives alone keep their target names
    jaw = np.array([args[1] for addr, args in rx.messages if addr == "/VMC/Ext/Blend/Val" and args[0] == "JawOpen"])
    assert jaw.max() > 0.6

    livecap("solve", take, "--rig", rig, "--out", tmp_path / "w.csv")
    livecap("rig", "animate", vrm, "--weights", tmp_path / "w.csv", "--out", tmp_path / "out.vrm")
    names, weights, _ = read_weights_csv(tmp_path / "w.csv")
    assert validate(tmp_path / "out.vrm")["issues"]["numErrors"] == 0
    import pygltflib as g

    doc = g.GLTF2.load_from_bytes((tmp_path / "out.vrm").read_bytes())
    acc = doc.accessors[doc.animations[0].samplers[0].output]
    view = doc.bufferViews[acc.bufferView]
    keys = np.frombuffer(doc.binary_blob(), np.float32, acc.count, view.byteOffset).reshape(len(weights), -1)
    assert keys.shape[1] == len(perf.names)  # every target of the face mesh, in its order
    np.testing.assert_allclose(keys[:, perf.names.index("jawOpen")], weights[:, names.index("JawOpen")], atol=1e-6)


@pytest.fixture(scope="module")
def solved_glb(avatar, tmp_path_factory) -> Path:
    """``livecap solve take.c3d --rig avatar.vrm --out take.glb``: one solve for the tests that animate it."""
    vrm, take, _ = avatar
    out = tmp_path_factory.mktemp("solved") / "take.glb"
    livecap("solve", take, "--rig", vrm, "--out", out)
    return out


def test_the_solves_head_rotation_turns_the_vrms_head_bone(avatar, solved_glb, tmp_path):
    """``solve --out take.glb`` then ``rig animate avatar.vrm --weights take.glb``: three.js plays the VRM 0's
    head bone turned as the actor's head turned (truth, relative to the neutral second) within 2 degrees, the
    VRM's -Z facing and the bone's rest rotation undone."""
    from scipy.spatial.transform import Rotation

    from tests.rig_writers import PARENT_Q

    vrm, _, perf = avatar
    done = livecap("rig", "animate", vrm, "--weights", solved_glb, "--out", tmp_path / "out.vrm")
    assert "and the head bone" in done.stdout
    assert validate(tmp_path / "out.vrm")["issues"]["numErrors"] == 0
    node = shutil.which("node")
    if node is None or not (TOOL / "node_modules" / "three").is_dir():
        pytest.skip(f"three.js not installed (run ./dev: needs node and npm install in {TOOL})")
    truth = Rotation.from_quat(perf.head_rotation)
    rel = truth * Rotation.from_quat(perf.head_rotation[:120]).mean().inv()  # world turn from the neutral second
    frames = [int(np.argmax(rel.magnitude())), 200]
    played = json.loads(subprocess.run([node, str(TOOL / "three_play.mjs"), str(tmp_path / "out.vrm"),
                                        *(str(f / 120.0) for f in frames)],
                                       capture_output=True, text=True, timeout=120, check=True).stdout)
    flip = Rotation.from_euler("y", 180, degrees=True)  # the rig's axes are VRM 0's turned about +Y
    for f, got in zip(frames, played["frames"], strict=True):
        turn = Rotation.from_quat(got["rotations"]["Head"]) * Rotation.from_quat(PARENT_Q).inv()
        err = (flip * turn * flip.inv() * rel[f].inv()).magnitude()
        assert np.degrees(err) < 2.0, (f, np.degrees(rel[f].magnitude()), np.degrees(err))
    assert np.degrees(rel[frames[0]].magnitude()) > 10


def _vrm_tools() -> str:
    node = shutil.which("node")
    if node is None or not (TOOL / "node_modules" / "@pixiv" / "three-vrm-animation").is_dir():
        pytest.skip(f"three-vrm not installed (run ./dev: needs node and npm install in {TOOL})")
    return node


def test_a_vrm_runtime_resets_a_weights_animation_but_plays_the_vrma(avatar, solved_glb, tmp_path):
    """three-vrm (@pixiv/three-vrm, the VRM runtime of three.js apps) reads the avatar's expressions as the
    importer does; it resets the morph targets they bind on every update, so the weights animation in the
    .vrm is lost there, while the .vrma (``rig animate --out take.vrma``) drives those expressions: the face's
    targets follow the solve to 1e-6 and the head bone turns as the actor's head within 2 degrees."""
    from scipy.spatial.transform import Rotation

    node = _vrm_tools()
    vrm, _, perf = avatar
    livecap("rig", "animate", vrm, "--weights", solved_glb, "--out", tmp_path / "out.vrm")
    livecap("rig", "animate", vrm, "--weights", solved_glb, "--out", tmp_path / "take.vrma")
    assert validate(tmp_path / "take.vrma")["issues"]["numErrors"] == 0

    def run(*args) -> dict:
        return json.loads(subprocess.run([node, *map(str, args)], capture_output=True, text=True, timeout=120,
                                         check=True).stdout)

    seen = run(TOOL / "vrm_expressions.mjs", vrm)["expressions"]
    table = import_rig(vrm).expressions
    vrm1 = {"A": "aa", "Blink": "blink"}  # three-vrm names VRM 0.x presets as VRM 1.0 does
    assert {vrm1.get(e, e): b for e, b in table.items()} == {e: m["FaceNode"] for e, m in seen.items()}

    t = 2.0
    wiped = run(TOOL / "vrm_expressions.mjs", tmp_path / "out.vrm", t)["played"]
    jaw = perf.names.index("jawOpen")
    assert wiped["before"]["FaceNode"][jaw] > 0.3 and wiped["after"]["FaceNode"][jaw] == 0.0

    from transport.rig_gltf_anim import read_solved_glb

    names, times, weights, rotation = read_solved_glb(solved_glb)
    frames = [int(np.argmax(Rotation.from_quat(rotation).magnitude())), int(t * 120)]
    played = run(TOOL / "vrma_play.mjs", vrm, tmp_path / "take.vrma", *(times[f] for f in frames))
    keyed = [names.index(s) for s in ("jawOpen", "eyeBlink_L", "mouthSmile_L")]
    flip = Rotation.from_euler("y", 180, degrees=True)  # the rig's axes are VRM 0's turned about +Y
    truth = Rotation.from_quat(perf.head_rotation)
    rel = truth * Rotation.from_quat(perf.head_rotation[:120]).mean().inv()
    for f, got in zip(frames, played["frames"], strict=True):
        np.testing.assert_allclose(np.array(got["FaceNode"])[keyed], weights[f, keyed], atol=1e-6)
        err = (flip.inv() * Rotation.from_quat(got["head"]) * flip * rel[f].inv()).magnitude()
        assert np.degrees(err) < 2.0, (f, np.degrees(rel[f].magnitude()), np.degrees(err))
    assert weights[frames[1], keyed[0]] > 0.3


def test_the_review_page_shows_the_solve_on_the_vrm(avatar, tmp_path):
    """``livecap review TAKE --rig avatar.vrm`` in chromium: the page loads the avatar's rig (three.js), draws
    its face, and scrubbing to the open jaw shows the served weights and a changed silhouette."""
    from tests.review_server import ReviewServer
    from tests.test_review_browser import CHROMIUM, DRIVER, browse, face_mask, wait

    if not (CHROMIUM.exists() and DRIVER.exists()):
        pytest.skip("Debian chromium + chromium-driver not installed (./dev test installs them)")
    vrm, take, perf = avatar
    server = ReviewServer(tmp_path, take=take, rig=vrm)
    try:
        with browse(server) as (driver, _):
            meta = server.get("/api/meta")
            assert meta["rig_names"] == perf.names and meta["n_frames"] == 300
            canvas = driver.find_element("id", "face")
            rest = face_mask(canvas.screenshot_as_png)
            assert rest.mean() > 0.01, "no face drawn"
            peak = 225  # jawOpen 0.77 in the take
            driver.execute_script(f"const f = document.getElementById('frame'); f.value = {peak};"
                                  "f.dispatchEvent(new Event('change'));")
            frame = wait(driver, "return window.review.current && window.review.current.frame > 150 && "
                         "window.review.current.frame", what="the scrub")
            assert abs(frame - peak) <= 3
            shown = driver.execute_script("return window.review.current.weights")
            np.testing.assert_allclose(shown, server.get(f"/api/frame/{frame}")["weights"], atol=1e-9)
            assert shown[meta["names"].index("jawOpen")] > 0.5
            time.sleep(0.3)
            opened = face_mask(canvas.screenshot_as_png)
            assert (opened != rest).mean() > 0.002, "the open jaw does not change the drawn face"
    finally:
        server.close()


def test_a_profile_calibrated_on_the_vrm_is_accepted_beside_it(avatar, tmp_path):
    """``solve --profile`` checks the profile against ``--rig``: a VRM is read for that (it was refused as
    'not a livecap rig file'), and another rig is still refused."""
    vrm, take, _ = avatar
    livecap("calibrate", take, "--rig", vrm, "--span", "0:1", "--out", tmp_path / "p.npz")
    livecap("solve", take, "--rig", vrm, "--profile", tmp_path / "p.npz", "--out", tmp_path / "w.csv")
    assert read_weights_csv(tmp_path / "w.csv")[1].shape[0] == 300
    done = subprocess.run([sys.executable, "-m", "livecap", "solve", take, "--rig", ICT, "--profile",
                           tmp_path / "p.npz", "--out", tmp_path / "x.csv"], capture_output=True, text=True)
    assert done.returncode == 1 and "recalibrate" in done.stderr and done.stderr.count("\n") == 1, done.stderr
