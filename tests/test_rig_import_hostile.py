"""Hostile rig files: every malformed glTF / VRM / USD gives one RigError naming the file (so the CLI prints
one line), never another exception. Each case breaks one thing in a valid file written by pygltflib / pxr."""

from __future__ import annotations

import numpy as np
import pytest

from livecap.core.rig import RigError
from tests.rig_writers import ObjRig, write_gltf, write_usd
from transport.rig_files import import_rig


def _rig() -> ObjRig:
    rng = np.random.default_rng(1)
    return ObjRig(rng.uniform(-0.1, 0.1, (30, 3)), np.array([[0, 1, 2], [2, 3, 4]]), ["jawOpen", "eyeBlink_L"],
                  rng.normal(0, 0.005, (2, 30, 3)))


def _face(doc):
    return doc.meshes[2].primitives[0]


BREAKS = {
    "target accessor past the list": lambda d: _face(d).targets[0].__setitem__("POSITION", 999),
    "unknown component type": lambda d: setattr(d.accessors[_face(d).attributes.POSITION], "componentType", 1234),
    "count past the buffer": lambda d: setattr(d.accessors[_face(d).attributes.POSITION], "count", 10 ** 6),
    "buffer view past its buffer": lambda d: setattr(d.bufferViews[0], "byteOffset", 10 ** 7),
    "indices accessor past the list": lambda d: setattr(_face(d), "indices", 999),
    "index past the vertices": lambda d: setattr(_face(d).attributes, "POSITION",
                                                 d.meshes[0].primitives[0].attributes.POSITION),
    "child node past the list": lambda d: d.nodes[0].children.append(999),
    "a node its own child": lambda d: d.nodes[2].children.append(2),
    "mesh node past the list": lambda d: setattr(d.nodes[3], "mesh", 99),
    "VRM binds not a list": lambda d: d.extensions["VRMC_vrm"]["expressions"]["preset"]["aa"].__setitem__(
        "morphTargetBinds", "jaw"),
    "VRM bind of a missing node": lambda d: d.extensions["VRMC_vrm"]["expressions"]["preset"]["aa"][
        "morphTargetBinds"][0].__setitem__("node", 77),
    "accessor type unknown": lambda d: setattr(d.accessors[_face(d).attributes.POSITION], "type", "VEC7"),
    "required Draco extension": lambda d: setattr(d, "extensionsRequired", ["KHR_draco_mesh_compression"]),
}


@pytest.mark.parametrize("name", sorted(BREAKS))
def test_a_broken_gltf_is_one_rig_error(tmp_path, name):
    import pygltflib as g

    doc = g.GLTF2.load_from_bytes(write_gltf(tmp_path / "ok.vrm", _rig(), vrm=1).read_bytes())
    BREAKS[name](doc)
    path = tmp_path / "broken.vrm"
    path.write_bytes(b"".join(doc.save_to_bytes()))
    try:
        import_rig(path)
    except RigError as exc:
        assert str(exc).startswith(str(path)) and "\n" not in str(exc)


@pytest.mark.parametrize("cut", [0, 12, 20, 100, 1000, -8])
def test_a_truncated_glb_is_one_rig_error(tmp_path, cut):
    data = write_gltf(tmp_path / "ok.glb", _rig()).read_bytes()
    (tmp_path / "cut.glb").write_bytes(data[:cut])
    with pytest.raises(RigError, match="cut.glb"):
        import_rig(tmp_path / "cut.glb")


def test_broken_usd_files_are_one_rig_error(tmp_path):
    pytest.importorskip("pxr", reason="usd-core not installed (pip install -e .[dev])")
    from pxr import Usd, UsdSkel, Vt

    (tmp_path / "junk.usda").write_text("#usda 1.0\n( garbage")
    with pytest.raises(RigError, match="junk.usda"):
        import_rig(tmp_path / "junk.usda")
    path = write_usd(tmp_path / "face.usda", _rig(), 1.0, "Y")
    stage = Usd.Stage.Open(str(path))
    blink = UsdSkel.BlendShape(stage.GetPrimAtPath("/Root/Head/Face/eyeBlink_L"))
    blink.GetPointIndicesAttr().Set(Vt.IntArray([0, 99]))
    stage.GetRootLayer().Save()
    with pytest.raises(RigError, match="pointIndices"):
        import_rig(path)
    stage = Usd.Stage.Open(str(path))
    UsdSkel.BindingAPI(stage.GetPrimAtPath("/Root/Head/Face")).GetBlendShapesAttr().Set(Vt.TokenArray(["jawOpen"]))
    stage.GetRootLayer().Save()
    with pytest.raises(RigError, match="1 blend shape names but 2"):
        import_rig(path)
