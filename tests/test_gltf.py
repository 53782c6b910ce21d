"""glTF 2.0 export checked by third-party code: the Khronos validator (npm) and pygltflib's reader."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pygltflib
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from livecap.core.headpose import NeutralPose, to_unity
from livecap.core.rig import Rig
from tests.conftest import ROOT
from tests.gltf_validator import animation_warnings, three_load, validate
from transport.gltf import glb_bytes, write_glb
from transport.takefile import read_take, write_take
from transport.weights_csv import write_weights_csv

DEMO_RIG = ROOT / "recordings" / "demo_rig.npz"


def _accessor(doc: pygltflib.GLTF2, index: int, width: int) -> np.ndarray:
    acc = doc.accessors[index]
    view = doc.bufferViews[acc.bufferView]
    blob = doc.binary_blob()
    raw = np.frombuffer(blob[view.byteOffset: view.byteOffset + view.byteLength], dtype=np.float32)
    return raw.reshape(acc.count, width) if width > 1 else raw


@pytest.fixture(scope="module")
def rig() -> Rig:
    return Rig.load(DEMO_RIG)


def test_glb_is_valid_and_carries_mesh_targets_and_curves(rig, tmp_path):
    rng = np.random.default_rng(1)
    T = 40
    times = np.arange(T) / 60.0
    names = rig.names[::-1][:30]  # a subset, in another order: matched by name
    weights = rng.uniform(0, 1, (T, len(names)))
    quats = Rotation.from_rotvec(rng.normal(0, 0.1, (T, 3))).as_quat()
    shift = rng.normal(0, 0.01, (T, 3))
    path = tmp_path / "take.glb"
    write_glb(path, rig, names, times, weights, quats, shift)

    report = validate(path)
    assert report["issues"]["numErrors"] == 0 and report["issues"]["numWarnings"] == 0, report["issues"]
    assert report["info"]["hasMorphTargets"] and report["info"]["animationCount"] == 1

    doc = pygltflib.GLTF2.load(str(path))
    mesh = doc.meshes[0]
    assert mesh.extras["targetNames"] == rig.names
    assert len(mesh.primitives[0].targets) == rig.n_shapes
    np.testing.assert_allclose(_accessor(doc, mesh.primitives[0].attributes.POSITION, 3), rig.neutral / 1000,
                               atol=1e-6)
    anim = doc.animations[0]
    paths = {c.target.path: anim.samplers[c.sampler] for c in anim.channels}
    assert set(paths) == {"weights", "rotation", "translation"}
    np.testing.assert_allclose(_accessor(doc, paths["weights"].input, 1), times, atol=1e-6)
    curves = _accessor(doc, paths["weights"].output, 1).reshape(T, rig.n_shapes)
    for j, n in enumerate(names):
        np.testing.assert_allclose(curves[:, rig.names.index(n)], weights[:, j], atol=1e-6)
    absent = [rig.names.index(n) for n in rig.names if n not in names]
    assert np.all(curves[:, absent] == 0)
    np.testing.assert_allclose(np.abs(np.sum(_accessor(doc, paths["rotation"].output, 4) * quats, axis=1)), 1,
                               atol=1e-5)


def _area_weighted_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Reference: per vertex, the sum over its triangles of area x unit face normal, normalised."""
    total = np.zeros_like(vertices)
    for a, b, c in triangles:
        n = np.cross(vertices[b] - vertices[a], vertices[c] - vertices[a])
        area = np.linalg.norm(n) / 2
        if area > 0:
            total[[a, b, c]] += area * n / np.linalg.norm(n)
    return total / np.linalg.norm(total, axis=1, keepdims=True)


def test_glb_normals_are_the_meshes_area_weighted_normals(rig, tmp_path):
    path = tmp_path / "take.glb"
    write_glb(path, rig, rig.names[:1], np.array([0.0]), np.zeros((1, 1)))
    report = validate(path)  # NORMAL must be unit length, target NORMALs any delta
    assert report["issues"]["numErrors"] == 0 and report["issues"]["numWarnings"] == 0, report["issues"]
    doc = pygltflib.GLTF2.load(str(path))
    prim = doc.meshes[0].primitives[0]
    assert prim.attributes.NORMAL is not None
    base = _accessor(doc, prim.attributes.NORMAL, 3)
    np.testing.assert_allclose(base, _area_weighted_normals(rig.neutral, rig.triangles), atol=1e-5)
    assert all("NORMAL" in t for t in prim.targets)
    for k in (0, rig.n_shapes // 2, rig.n_shapes - 1):  # base + delta, renormalised as a renderer does
        shaded = base + _accessor(doc, prim.targets[k]["NORMAL"], 3)
        shaded /= np.linalg.norm(shaded, axis=1, keepdims=True)
        np.testing.assert_allclose(shaded, _area_weighted_normals(rig.neutral + rig.deltas[k], rig.triangles),
                                   atol=1e-4)
    three = three_load(path)  # three.js takes the file's normals instead of computing flat ones
    assert three["targetNormals"] == rig.n_shapes
    np.testing.assert_allclose(three["normals"], base[:10].reshape(-1), atol=1e-6)


def test_glb_rejects_bad_curves(rig):
    with pytest.raises(ValueError, match="noSuchShape"):
        glb_bytes(rig, ["noSuchShape"], np.array([0.0]), np.zeros((1, 1)))
    with pytest.raises(ValueError, match="strictly increasing"):
        glb_bytes(rig, rig.names[:1], np.array([0.0, 0.0]), np.zeros((2, 1)))


def _short_take(tmp_path, frames: int = 180):
    path = tmp_path / "short.c3d"
    write_take(read_take(ROOT / "recordings" / "demo_take.c3d").slice(0, frames), path)
    return path


def test_solve_and_export_write_valid_glb(tmp_path):
    take = _short_take(tmp_path)
    glb = tmp_path / "solved.glb"
    cmd = [sys.executable, "-m", "livecap", "solve", str(take), "--rig", str(DEMO_RIG), "--out", str(glb)]
    subprocess.run(cmd, check=True, capture_output=True, timeout=300)
    report = validate(glb)
    assert report["issues"]["numErrors"] == 0 and animation_warnings(report) == [], report["issues"]
    three = three_load(glb)  # as a browser viewer loads it
    assert three["vertices"] == Rig.load(DEMO_RIG).n_vertices and three["targets"] == Rig.load(DEMO_RIG).names
    assert {t["name"]: t["times"] for t in three["tracks"]} == {
        "head.morphTargetInfluences": 180, "head.quaternion": 180, "head.position": 180}
    assert three["duration"] == pytest.approx(179 / 120, abs=1e-4)
    doc = pygltflib.GLTF2.load(str(glb))
    anim = doc.animations[0]
    rot = next(anim.samplers[c.sampler] for c in anim.channels if c.target.path == "rotation")
    q = _accessor(doc, rot.output, 4)
    assert len(q) == 180
    # relative to the neutral window (the first second): its mean pose is the identity, later ones not
    assert np.degrees(Rotation.from_quat(q[:120]).mean().magnitude()) < 0.1  # 1 s at 120 Hz
    assert np.degrees(Rotation.from_quat(q).magnitude()).max() > 1.0

    csv = tmp_path / "w.csv"
    rng = np.random.default_rng(2)
    rig = Rig.load(DEMO_RIG)
    write_weights_csv(csv, rig.names, rng.uniform(0, 1, (50, rig.n_shapes)), 60.0)
    out = tmp_path / "exported.glb"
    done = subprocess.run([sys.executable, "-m", "livecap", "export", str(csv), "--rig", str(DEMO_RIG), "--out",
                           str(out)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    report = validate(out)
    assert report["issues"]["numErrors"] == 0 and report["issues"]["numWarnings"] == 0, report["issues"]


def test_export_names_a_bad_weights_file(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("a,b\n1,2\n")
    done = subprocess.run([sys.executable, "-m", "livecap", "export", str(bad), "--rig", str(DEMO_RIG), "--out",
                           str(tmp_path / "x.glb")], capture_output=True, text=True, timeout=120)
    assert done.returncode == 1 and "bad.csv" in done.stderr and len(done.stderr.strip().splitlines()) == 1


_quat = st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 0.1)


@given(_quat, _quat, st.lists(st.floats(-2000, 2000), min_size=3, max_size=3))
def test_neutral_pose_is_identity_on_itself_and_composes(q0, q1, t0):
    """Relative to itself the neutral is the identity; a turn applied in head axes comes back as that turn."""
    q0 = np.array(q0) / np.linalg.norm(q0)
    neutral = NeutralPose.mean_of(q0[None], np.array(t0)[None])
    rel, shift = neutral.relative(q0, np.array(t0))
    assert Rotation.from_quat(rel).magnitude() < 1e-6 and np.allclose(shift, 0)
    turn = Rotation.from_quat(q1)
    rel, _ = neutral.relative((Rotation.from_quat(q0) * turn).as_quat(), np.array(t0))
    assert (Rotation.from_quat(rel) * turn.inv()).magnitude() < 1e-6
    qu, pu = to_unity(rel, np.array([1.0, 2.0, 3.0]))
    back_q, back_p = to_unity(qu, pu)
    assert np.allclose(back_q, rel) and np.allclose(back_p, [1, 2, 3]) and pu[0] == -1.0
