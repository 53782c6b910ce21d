"""FBX through Blender headless (docs/rigs.md): Blender writes an FBX of ICT shapes (tests/blender_fbx.py),
tools/blender/fbx_to_glb.py converts it to GLB as a user would, ``livecap rig import`` reads that. Blender's
glTF exporter splits every vertex per face corner; the importer welds them back, so the rig is the OBJ
folder's up to vertex order. Skipped where Debian's ``blender`` (and its ``python3-numpy``) is absent."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from livecap.core.rig import Rig
from tests.conftest import ICT
from tests.rig_writers import read_obj_rig
from transport.rig_files import import_rig
from transport.rig_gltf import _weld

ROOT = Path(__file__).resolve().parents[1]
NAMES = ["jawOpen", "eyeBlink_L", "mouthSmile_R"]


def blender(*args) -> subprocess.CompletedProcess:
    exe = shutil.which("blender")
    if exe is None:
        pytest.skip("Blender not installed (Debian: apt-get install blender python3-numpy)")
    done = subprocess.run([exe, "-b", "--factory-startup", "--python", *map(str, args)], capture_output=True,
                          text=True, timeout=300)
    if "No module named 'numpy'" in done.stdout + done.stderr:
        pytest.skip("Blender's Python has no numpy (Debian: apt-get install python3-numpy)")
    assert done.returncode == 0 and "Error" not in done.stdout, done.stdout[-2000:] + done.stderr[-2000:]
    return done


def test_fbx_converted_by_blender_gives_the_obj_folders_rig(tmp_path, ict):
    ref, _ = ict
    src = read_obj_rig(ICT, NAMES, 0.01)
    np.savez(tmp_path / "rig.npz", neutral=src.neutral, triangles=src.triangles, names=np.array(src.names),
             deltas=src.deltas)
    blender(ROOT / "tests" / "blender_fbx.py", "--", tmp_path / "rig.npz", tmp_path / "face.fbx")
    blender(ROOT / "tools" / "blender" / "fbx_to_glb.py", "--", tmp_path / "face.fbx", tmp_path / "face.glb")
    rig = import_rig(tmp_path / "face.glb").rig
    assert rig.names == NAMES and rig.n_vertices == ref.n_vertices  # 3 x 18460 corners welded to 9409
    dist, idx = cKDTree(ref.neutral).query(rig.neutral)
    assert dist.max() < 1e-4 and len(np.unique(idx)) == ref.n_vertices
    assert sorted(map(tuple, np.sort(idx[rig.triangles], 1))) == sorted(map(tuple, np.sort(ref.triangles, 1)))
    deltas = ref.deltas[[ref.index(n) for n in NAMES]][:, idx]
    np.testing.assert_allclose(rig.deltas, deltas, rtol=0, atol=1e-3)  # Blender's FBX drops offsets near 0


def test_weld_joins_copies_equal_in_every_target_and_keeps_first_order():
    neutral = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [1, 1, 0]])
    deltas = np.zeros((1, 5, 3))
    deltas[0, 4] = [0, 0, 1]
    tris = np.array([[0, 1, 2], [3, 4, 2]])
    n, t, d = _weld(neutral, tris, deltas)
    assert n.tolist() == [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]
    assert t.tolist() == [[0, 1, 2], [1, 3, 2]] and d[0, 3].tolist() == [0, 0, 1]
    deltas[0, 3] = [0, 0, 0.5]  # a copy that a target moves apart is a vertex of its own
    assert len(_weld(neutral, tris, deltas)[0]) == 5
    assert Rig(n, t, ["a"], d).n_vertices == 4
