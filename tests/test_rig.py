import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from livecap.core.objfile import ObjError, write_obj
from livecap.core.rig import Rig, RigError


def tiny_rig():
    neutral = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    tris = np.array([[0, 1, 2]])
    faces = {
        "a": neutral + np.array([[1.0, 0, 0], [0, 0, 0], [0, 0, 0]]),
        "b": neutral + np.array([[0.0, 2, 0], [0, 0, 1], [0, 0, 0]]),
        "c": neutral + np.array([[0.0, 0, 0], [0, 0, 0], [0, 0, 3]]),
        "a@0.5": neutral + np.array([[0.5, 0.4, 0], [0, 0, 0], [0, 0, 0]]),
        "a+b": neutral + np.array([[1.0, 2, 0], [0, 0, 1], [0, 0, 0]]) + np.array([[0, 0, 0.25], [0, 0, 0], [0, 0, 0]]),
        "a+b+c": neutral + np.array([[1.0, 2, 0.25], [0, 0, 1], [0, 0, 3]])
        + np.array([[0, 0, 0], [0, 1.0, 0], [0, 0, 0]]),
    }
    return Rig.from_whole_face(neutral, tris, faces), neutral


def test_evaluate_hand_computed():
    rig, neutral = tiny_rig()
    assert rig.names == ["a", "b", "c"]
    # a = 1 sits past its in-between, so only the straight part and the a+b corrective count
    out = rig.evaluate(np.array([1.0, 0.5, 0.0]))
    linear = np.array([[1.0, 1.0, 0.0], [0, 0, 0.5], [0, 0, 0]])
    expected = neutral + linear + np.array([[0, 0, 0.25 * 0.5], [0, 0, 0], [0, 0, 0]])
    np.testing.assert_allclose(out, expected)


def test_inbetween_piecewise_linear():
    rig, neutral = tiny_rig()
    at = lambda w: rig.evaluate(np.array([w, 0.0, 0.0]))[0]  # noqa: E731
    np.testing.assert_allclose(at(0.5), [0.5, 0.4, 0])  # exactly the sculpt
    np.testing.assert_allclose(at(0.25), [0.25, 0.2, 0])  # halfway to it
    np.testing.assert_allclose(at(0.75), [0.75, 0.2, 0])  # halfway from it to the full shape
    np.testing.assert_allclose(at(1.0), [1.0, 0, 0])
    np.testing.assert_allclose(at(1.5), [1.5, 0, 0])  # beyond the limits: linear
    np.testing.assert_allclose(at(-0.5), [-0.5, 0, 0])


def test_correctives_products():
    rig, neutral = tiny_rig()
    # the sculpts are reproduced at the hypercube corners
    for name, face in rig.whole_face().items():
        w = np.zeros(3)
        if "@" in name:
            base, wt = name.split("@")
            w[rig.index(base)] = float(wt)
        else:
            for part in name.split("+"):
                w[rig.index(part)] = 1.0
        np.testing.assert_allclose(rig.evaluate(w), face, atol=1e-12)
    # triple corrective scales with the product of its three weights
    w = np.array([0.5, 0.5, 0.5])
    full = rig.evaluate(w)
    lin = neutral + np.einsum("m,mvc->vc", w, rig.deltas)
    pair = 0.25 * np.array([[0, 0, 0.25], [0, 0, 0], [0, 0, 0]])
    triple = 0.125 * np.array([[0, 0, 0], [0, 1.0, 0], [0, 0, 0]])
    inbetween = np.array([[0, 0.4, 0], [0, 0, 0], [0, 0, 0]])  # a = 0.5 sits on its in-between sculpt
    np.testing.assert_allclose(full, lin + pair + triple + inbetween, atol=1e-12)


def test_evaluate_vectorised_matches_loop(demo):
    rig, _ = demo
    W = np.random.default_rng(0).uniform(0, 1, (5, rig.n_shapes))
    batch = rig.evaluate(W)
    for i in range(5):
        np.testing.assert_allclose(batch[i], rig.evaluate(W[i]), atol=1e-9)


def test_npz_and_obj_folder_round_trip(tmp_path, demo):
    rig, _ = demo
    rig.save(tmp_path / "r.npz")
    back = Rig.load(tmp_path / "r.npz")
    W = np.random.default_rng(1).uniform(0, 1, (3, rig.n_shapes))
    np.testing.assert_allclose(back.evaluate(W), rig.evaluate(W), atol=1e-3)  # float32 storage
    rig.save_obj_folder(tmp_path / "objs")
    back2 = Rig.load(tmp_path / "objs")
    assert back2.names == rig.names
    assert len(back2.inbetweens) == len(rig.inbetweens) and len(back2.correctives) == len(rig.correctives)
    np.testing.assert_allclose(back2.evaluate(W), rig.evaluate(W), atol=1e-4)


def test_obj_folder_in_centimetres(tmp_path):
    (tmp_path / "neutral.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 4 3\n")
    (tmp_path / "smile.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0.5\nf 1/1/1 2/2/2 4/4/4 3/3/3\n")  # a quad, with uv/normal refs
    (tmp_path / "rig.json").write_text('{"units": "cm"}')
    rig = Rig.load(tmp_path)
    np.testing.assert_allclose(rig.deltas[0][3], [0, 0, 5.0])  # 0.5 cm -> 5 mm


def test_real_ict_rig_loads(ict):
    rig, layout = ict
    assert rig.n_shapes == 53 and rig.n_vertices == 9409
    assert layout.n_markers == 60 and layout.stable.sum() >= 3
    assert "jawOpen" in rig.names
    # centimetres became millimetres: the face is about 18 cm wide
    assert 150 < np.ptp(rig.neutral[:, 0]) < 220
    jaw = layout.basis(rig)[:, rig.index("jawOpen")]
    assert np.abs(jaw).max() > 5  # opening the jaw moves some marker by more than 5 mm


def test_bad_rigs(tmp_path):
    with pytest.raises(RigError, match="no neutral.obj"):
        Rig.load(tmp_path)
    write_obj(tmp_path / "neutral.obj", np.eye(3), [[0, 1, 2]])
    write_obj(tmp_path / "extra.obj", np.vstack([np.eye(3), [[1, 1, 1]]]), [[0, 1, 2]])
    with pytest.raises(RigError, match="mismatched topology"):
        Rig.load(tmp_path)
    (tmp_path / "extra.obj").write_text("v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(RigError, match="NaN"):
        Rig.load(tmp_path)
    (tmp_path / "extra.obj").write_text("v 1 0 0\nv 0 1 0\nf 1 2 9\n")
    with pytest.raises((RigError, ObjError), match="extra.obj"):
        Rig.load(tmp_path)
    with pytest.raises(RigError, match="not a livecap rig"):
        (tmp_path / "x.npz").write_bytes(b"not a zip")
        Rig.load(tmp_path / "x.npz")


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-2, 3), min_size=3, max_size=3))
def test_whole_face_round_trip_is_exact(ws):
    rig, _ = tiny_rig()
    back = Rig.from_whole_face(rig.neutral, rig.triangles, rig.whole_face())
    np.testing.assert_allclose(back.evaluate(np.array(ws)), rig.evaluate(np.array(ws)), atol=1e-9)
