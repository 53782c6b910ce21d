"""Rig import (issue 37): glTF/GLB, VRM 0.x/1.0 and USD files written by third-party code (pygltflib, pxr,
three.js's GLTFExporter; tests/rig_writers.py) from the ICT and MakeHuman OBJ folders give back the OBJ
folder's rig: same names, triangles, vertices and deltas within 1e-5 of the rig's units (cm: 1e-4 mm)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from livecap.core.rig import Rig, RigError
from tests.conftest import ICT, SHARED
from tests.gltf_validator import validate
from tests.rig_writers import ObjRig, read_obj_rig, write_gltf, write_usd
from transport.rig_files import import_rig, load_rig

MAKEHUMAN = SHARED / "realdata" / "makehuman-head"
TOOL = Path(__file__).resolve().parents[1] / "tools" / "gltf"
SUBSET = ["eyeBlink_L", "eyeBlink_R", "jawOpen", "mouthSmile_L", "browInnerUp_R"]
TOL_MM = 1e-4  # 1e-5 of the OBJ folders' centimetres


def livecap(*args, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "livecap", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)


def _folder(path: Path) -> Path:
    if not (path / "neutral.obj").exists():
        pytest.skip(f"rig folder not found at {path} (../shared/realdata is not beside this checkout)")
    return path


@pytest.fixture(scope="module")
def ict_obj() -> tuple[Rig, ObjRig]:
    """The ICT OBJ folder as livecap reads it (mm) and the subset's faces in metres for the writers."""
    folder = _folder(ICT)
    return Rig.load(folder), read_obj_rig(folder, SUBSET, 0.01)


def assert_same_rig(got: Rig, ref: Rig, names: list[str] | None = None) -> None:
    names = ref.names if names is None else names
    assert got.names == names
    np.testing.assert_array_equal(got.triangles, ref.triangles)
    np.testing.assert_allclose(got.neutral, ref.neutral, rtol=0, atol=TOL_MM)
    np.testing.assert_allclose(got.deltas, ref.deltas[[ref.index(n) for n in names]], rtol=0, atol=TOL_MM)


@pytest.mark.parametrize("vrm, sparse, suffix", [(None, False, "glb"), (None, True, "glb"), (0, False, "vrm"),
                                                 (1, True, "vrm")])
def test_gltf_and_vrm_files_give_the_obj_folders_rig(tmp_path, ict_obj, vrm, sparse, suffix):
    """Node transforms (translated, turned, halved parent), sparse targets, VRM 0's -Z facing, metres; the
    face mesh chosen among Body (no targets) and Teeth (one target) by name or by the VRM's expressions."""
    ref, src = ict_obj
    imported = import_rig(write_gltf(tmp_path / f"avatar.{suffix}", src, vrm=vrm, sparse=sparse))
    assert imported.mesh == "Face" and set(imported.meshes) == {"Face", "Teeth"}
    assert imported.format == {None: "glTF", 0: "VRM 0.x", 1: "VRM 1.0"}[vrm]
    assert_same_rig(imported.rig, ref, SUBSET)


def test_a_skinned_face_is_read_at_its_rest_pose(tmp_path, ict_obj):
    """Skinned (Armature at scale 0.01, two joints blended 30/70, the mesh node's own transform ignored as
    glTF §3.7.3 says): joints' world matrices times inverse bind matrices give the OBJ folder's rig."""
    ref, src = ict_obj
    imported = import_rig(write_gltf(tmp_path / "skinned.vrm", src, vrm=1, skinned=True, sparse=True))
    assert_same_rig(imported.rig, ref, SUBSET)
    report = validate(tmp_path / "skinned.vrm")
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"][:3]


@pytest.mark.parametrize("version, preset", [(0, ("A", "Blink")), (1, ("aa", "blink"))])
def test_vrm_presets_and_perfect_sync_clips_map_to_the_face_targets(tmp_path, ict_obj, version, preset):
    _, src = ict_obj
    expr = import_rig(write_gltf(tmp_path / "avatar.vrm", src, vrm=version)).expressions
    assert expr[preset[0]] == {"jawOpen": 1.0}
    assert expr[preset[1]] == {"eyeBlink_L": 1.0, "eyeBlink_R": 1.0}
    assert expr["EyeBlinkLeft"] == {"eyeBlink_L": 1.0} and expr["MouthSmileLeft"] == {"mouthSmile_L": 1.0}
    assert expr["JawOpen"] == {"jawOpen": 1.0}


def test_vrm_shapes_named_by_the_expressions_that_drive_them_alone(tmp_path, ict_obj):
    """``rig import --names expressions``: Perfect Sync ``JawOpen`` (named like the target) wins over the preset
    ``A`` that also drives jawOpen alone; ``Blink`` drives two targets and renames none."""
    _, src = ict_obj
    vrm = write_gltf(tmp_path / "avatar.vrm", src, vrm=0)
    done = livecap("rig", "import", vrm, "--names", "expressions", "--out", tmp_path / "a.npz")
    assert done.returncode == 0, done.stderr
    assert Rig.load(tmp_path / "a.npz").names == ["EyeBlinkLeft", "EyeBlinkRight", "JawOpen", "MouthSmileLeft",
                                                  "BrowInnerUp"]
    table = json.loads((tmp_path / "a.expressions.json").read_text())["expressions"]
    assert table["Blink"] == {"EyeBlinkLeft": 1.0, "EyeBlinkRight": 1.0} and table["A"] == {"JawOpen": 1.0}
    done = livecap("rig", "import", write_gltf(tmp_path / "a.glb", src), "--names", "expressions", "--out", "x.npz")
    assert done.returncode == 1 and "no VRM expressions" in done.stderr


def test_markers_that_do_not_fit_the_mesh_stop_the_import_before_it_writes(tmp_path):
    folder = _folder(MAKEHUMAN)
    glb = write_gltf(tmp_path / "head.glb", read_obj_rig(folder, ["mouth-open"], 0.01))
    done = livecap("rig", "import", glb, "--out", tmp_path / "head.npz", "--markers", ICT / "markers.json")
    assert done.returncode == 1 and "outside the rig's 0..4259" in done.stderr
    assert not (tmp_path / "head.npz").exists()


@pytest.mark.parametrize("meters_per_unit, up", [(0.01, "Z"), (1.0, "Y")])
def test_usd_blend_shapes_give_the_obj_folders_rig(tmp_path, ict_obj, meters_per_unit, up):
    """metersPerUnit, a Z-up stage, the Xform above the mesh, dense and sparse (pointIndices) offsets."""
    pytest.importorskip("pxr", reason="usd-core not installed (pip install -e .[dev])")
    ref, src = ict_obj
    imported = import_rig(write_usd(tmp_path / "face.usda", src, meters_per_unit, up))
    assert imported.format == "USD" and imported.meshes == ("Face",)
    assert_same_rig(imported.rig, ref, SUBSET)


def test_usd_inbetweens_become_livecap_inbetweens(tmp_path, ict_obj):
    """A UsdSkel in-between at weight 0.5 evaluates to its sculpt at w = 0.5 (Lewis §3.2)."""
    pytest.importorskip("pxr", reason="usd-core not installed (pip install -e .[dev])")
    from pxr import Usd, UsdSkel, Vt

    ref, src = ict_obj
    path = write_usd(tmp_path / "face.usda", src, 1.0, "Y")
    stage = Usd.Stage.Open(str(path))
    jaw = UsdSkel.BlendShape(stage.GetPrimAtPath("/Root/Head/Face/jawOpen"))
    half = src.deltas[SUBSET.index("jawOpen")] * 0.3  # the sculpt at half way moves 0.3 of the full shape
    jaw.CreateInbetween("half").SetOffsets(Vt.Vec3fArray.FromNumpy(half.astype(np.float32)))
    jaw.GetInbetween("half").SetWeight(0.5)
    stage.GetRootLayer().Save()
    rig = import_rig(path).rig
    assert len(rig.inbetweens) == 1
    w = np.zeros(rig.n_shapes)
    w[rig.index("jawOpen")] = 0.5
    np.testing.assert_allclose(rig.evaluate(w), ref.neutral + half * 1000.0, atol=TOL_MM)


def test_a_glb_that_threejs_gltfexporter_wrote(tmp_path, ict_obj):
    """three.js (npm, tools/gltf/three_export.mjs) writes the face under a translated group: read back."""
    node = shutil.which("node")
    if node is None or not (TOOL / "node_modules" / "three").is_dir():
        pytest.skip(f"three.js not installed (run ./dev: needs node and npm install in {TOOL})")
    ref, src = ict_obj
    t = [0.0, 0.03, 0.01]
    spec = {"name": "face", "positions": (src.neutral - t).ravel().tolist(), "indices": src.triangles.ravel().tolist(),
            "names": src.names, "deltas": [d.ravel().tolist() for d in src.deltas], "translation": t}
    (tmp_path / "in.json").write_text(json.dumps(spec))
    subprocess.run([node, str(TOOL / "three_export.mjs"), str(tmp_path / "in.json"), str(tmp_path / "three.glb")],
                   check=True, timeout=60, capture_output=True)
    imported = import_rig(tmp_path / "three.glb")
    assert imported.mesh == "face"
    assert_same_rig(imported.rig, ref, SUBSET)


def test_whole_ict_rig_as_vrm_through_the_cli(tmp_path, ict_obj):
    """``livecap rig import`` of all 53 shapes (VRM 1.0) writes an .npz equal to the OBJ folder, the
    expression table and the markers beside it; the .vrm itself is a rig for ``livecap info``."""
    ref, _ = ict_obj
    vrm = write_gltf(tmp_path / "ict.vrm", read_obj_rig(ICT, None, 0.01), vrm=1, sparse=True)
    done = livecap("rig", "import", vrm, "--out", tmp_path / "ict.npz", "--markers", ICT / "markers.json")
    assert done.returncode == 0, done.stderr
    assert "VRM 1.0: mesh 'Face'" in done.stdout and "Teeth" in done.stdout
    rig = Rig.load(tmp_path / "ict.npz")
    assert_same_rig(rig, ref)
    table = json.loads((tmp_path / "ict.expressions.json").read_text())
    assert table["expressions"]["blink"] == {"eyeBlink_L": 1.0, "eyeBlink_R": 1.0}
    assert (tmp_path / "ict.markers.json").exists()
    info = livecap("info", vrm, "--markers", ICT / "markers.json")
    assert info.returncode == 0, info.stderr
    assert f"{ref.n_vertices} vertices" in info.stdout and "53 shapes" in info.stdout


def test_whole_makehuman_rig_as_usd_glb_and_vrm(tmp_path):
    pytest.importorskip("pxr", reason="usd-core not installed (pip install -e .[dev])")
    folder = _folder(MAKEHUMAN)
    ref = Rig.load(folder)
    usd = write_usd(tmp_path / "head.usdc", read_obj_rig(folder, None, 0.01), 0.01, "Z")
    done = livecap("rig", "import", usd, "--out", tmp_path / "head")
    assert done.returncode == 0, done.stderr
    assert_same_rig(Rig.load(tmp_path / "head"), ref)
    src = read_obj_rig(folder, None, 0.01)
    for vrm, name in ((None, "head.glb"), (0, "head0.vrm"), (1, "head1.vrm")):
        assert_same_rig(load_rig(write_gltf(tmp_path / name, src, vrm=vrm, sparse=vrm == 1)), ref)


def test_a_file_without_morph_targets_is_one_clear_line(tmp_path, ict_obj):
    import pygltflib as g

    _, src = ict_obj
    doc = g.GLTF2().load_from_bytes(write_gltf(tmp_path / "a.glb", src).read_bytes())
    for m in doc.meshes:
        for p in m.primitives:
            p.targets = []
    doc.save_binary(str(tmp_path / "static.glb"))
    done = livecap("rig", "import", tmp_path / "static.glb", "--out", tmp_path / "r.npz")
    assert done.returncode == 1
    assert done.stderr.strip().count("\n") == 0 and "no mesh with morph targets" in done.stderr
    assert "static.glb" in done.stderr
    (tmp_path / "junk.vrm").write_bytes(b"glTF\x02\x00\x00\x00garbage")
    done = livecap("solve", tmp_path / "none.c3d", "--rig", tmp_path / "junk.vrm", "--out", tmp_path / "w.csv")
    assert done.returncode == 1 and done.stderr.strip().count("\n") == 0 and "junk.vrm" in done.stderr


def test_the_mesh_is_chosen_by_flag_or_name_and_ambiguity_is_an_error(tmp_path, ict_obj):
    import pygltflib as g

    _, src = ict_obj
    path = write_gltf(tmp_path / "a.glb", src)
    assert import_rig(path, "Teeth").rig.names == ["jawOpen"]
    assert import_rig(path, "teeth").mesh == "Teeth"
    with pytest.raises(RigError, match="no mesh with blend shapes named 'Tongue'.*Teeth, Face"):
        import_rig(path, "Tongue")
    doc = g.GLTF2().load_from_bytes(path.read_bytes())
    doc.meshes[2].name = "Body_001"
    doc.nodes[3].name = None
    doc.save_binary(str(tmp_path / "b.glb"))
    with pytest.raises(RigError, match="none named face or head.*--mesh"):
        import_rig(tmp_path / "b.glb")
    with pytest.raises(RigError, match="only applies to glTF"):
        load_rig(ICT, mesh="Face")


@pytest.mark.parametrize("form", ["bin file", "data uri"])
def test_json_gltf_with_external_or_embedded_buffers(tmp_path, ict_obj, form):
    """A .gltf (JSON) whose buffer is a .bin beside it or a base64 data URI (pygltflib converts the GLB);
    ``rig animate`` packs it into a GLB container."""
    import pygltflib as g

    ref, src = ict_obj
    doc = g.GLTF2.load_from_bytes(write_gltf(tmp_path / "a.glb", src, sparse=True).read_bytes())
    doc._path = tmp_path
    doc.convert_buffers(g.BufferFormat.BINFILE if form == "bin file" else g.BufferFormat.DATAURI)
    doc.save_json(str(tmp_path / "face.gltf"))
    imported = import_rig(tmp_path / "face.gltf")
    assert_same_rig(imported.rig, ref, SUBSET)
    (tmp_path / "w.csv").write_text("frame,time,jawOpen\n0,0,0\n1,0.5,0.7\n")
    done = livecap("rig", "animate", tmp_path / "face.gltf", "--weights", tmp_path / "w.csv", "--out",
                   tmp_path / "out.glb")
    assert done.returncode == 0, done.stderr
    assert_same_rig(import_rig(tmp_path / "out.glb").rig, ref, SUBSET)
    assert validate(tmp_path / "out.glb")["issues"]["numErrors"] == 0
    assert form != "bin file" or (tmp_path / "0.bin").exists()


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(t=arrays(np.float64, 3, elements=st.floats(-2, 2)), q=arrays(np.float64, 4, elements=st.floats(-1, 1)),
       scale=st.floats(0.01, 100), as_matrix=st.booleans())
def test_any_parent_transform_is_undone(tmp_path, t, q, scale, as_matrix):
    """Whatever rigid + uniform-scale transform the face's parent node has (as TRS or as one column-major
    matrix), the imported rig is the source: positions through the whole world matrix, deltas through its
    linear part."""
    assume(np.linalg.norm(q) > 0.1)
    q = q / np.linalg.norm(q)
    rng = np.random.default_rng(0)
    src = ObjRig(rng.uniform(-0.1, 0.1, (30, 3)), np.array([[0, 1, 2], [2, 3, 4]]), ["a", "b"],
                 rng.normal(0, 0.005, (2, 30, 3)))
    got = import_rig(write_gltf(tmp_path / "t.glb", src, parent=(t, q, scale), as_matrix=as_matrix)).rig
    tol = 1e-3 * (0.2 + np.abs(t).max())  # mm: ~4 float32 steps of the stored local coordinates, scaled back
    np.testing.assert_allclose(got.neutral, src.neutral * 1000, atol=tol)
    np.testing.assert_allclose(got.deltas, src.deltas * 1000, atol=tol)


def test_quantized_positions_and_targets(tmp_path):
    """KHR_mesh_quantization (what gltfpack writes): normalized int16 positions and int8 targets (strided to 8
    and 4 bytes), dequantized by the node's scale; read back to within half a quantization step."""
    import pygltflib as g

    rng = np.random.default_rng(2)
    neutral = rng.uniform(-0.1, 0.1, (40, 3))
    delta = rng.uniform(-0.01, 0.01, (40, 3))
    q_pos = np.zeros((40, 4), np.int16)
    q_pos[:, :3] = np.round(neutral / 0.1 * 32767)
    q_delta = np.zeros((40, 4), np.int8)
    q_delta[:, :3] = np.round(delta / 0.1 * 127)
    blob = q_pos.tobytes() + q_delta.tobytes()
    blob += b"\0" * (-len(blob) % 4)
    doc = g.GLTF2(asset=g.Asset(version="2.0"), scene=0, scenes=[g.Scene(nodes=[0])],
                  extensionsUsed=["KHR_mesh_quantization"], extensionsRequired=["KHR_mesh_quantization"],
                  buffers=[g.Buffer(byteLength=len(blob))],
                  bufferViews=[g.BufferView(buffer=0, byteOffset=0, byteLength=q_pos.nbytes, byteStride=8),
                               g.BufferView(buffer=0, byteOffset=q_pos.nbytes, byteLength=q_delta.nbytes,
                                            byteStride=4)],
                  accessors=[g.Accessor(bufferView=0, componentType=g.SHORT, normalized=True, count=40, type=g.VEC3,
                                        min=q_pos[:, :3].min(0).tolist(), max=q_pos[:, :3].max(0).tolist()),
                             g.Accessor(bufferView=1, componentType=g.BYTE, normalized=True, count=40, type=g.VEC3,
                                        min=q_delta[:, :3].min(0).tolist(), max=q_delta[:, :3].max(0).tolist())],
                  meshes=[g.Mesh(name="face", extras={"targetNames": ["open"]}, primitives=[g.Primitive(
                      attributes=g.Attributes(POSITION=0), targets=[{"POSITION": 1}], mode=g.POINTS)])],
                  nodes=[g.Node(mesh=0, scale=[0.1] * 3)])
    doc.set_binary_blob(blob)
    doc.save_binary(str(tmp_path / "q.glb"))
    report = validate(tmp_path / "q.glb")
    assert report["issues"]["numErrors"] == 0, [m for m in report["issues"]["messages"] if m["severity"] == 0]
    rig = import_rig(tmp_path / "q.glb").rig
    np.testing.assert_allclose(rig.neutral, neutral * 1000, atol=0.1 / 32767 * 1000 * 0.51)
    np.testing.assert_allclose(rig.deltas[0], delta * 1000, atol=0.1 / 127 * 1000 * 0.51)
