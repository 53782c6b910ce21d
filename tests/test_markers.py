import json

import numpy as np
import pytest

from livecap.core.markers import LayoutError, MarkerLayout


def test_basis_matches_evaluate(demo):
    rig, layout = demo
    B = layout.basis(rig)
    assert B.shape == (3 * layout.n_markers, rig.n_shapes)
    w = np.zeros(rig.n_shapes)
    w[rig.index("mouthSmileLeft")] = 0.7
    sites = rig.evaluate(w)[layout.vertices[:, 0]]
    np.testing.assert_allclose((B @ w).reshape(-1, 3) + rig.neutral[layout.vertices[:, 0]], sites, atol=1e-9)


def test_marker_rig_keeps_nonlinear_parts(demo):
    rig, layout = demo
    W = np.random.default_rng(3).uniform(0, 1, (4, rig.n_shapes))
    np.testing.assert_allclose(layout.marker_rig(rig).evaluate(W), rig.evaluate(W)[:, layout.vertices[:, 0]],
                               atol=1e-9)


def test_triangle_binding(tmp_path, demo):
    rig, _ = demo
    t = 100
    (tmp_path / "m.json").write_text(json.dumps({"units": "mm", "markers": [
        {"label": "a", "triangle": t, "barycentric": [0.2, 0.3, 0.5], "stable": True}]}))
    layout = MarkerLayout.load(tmp_path / "m.json", rig)
    expected = np.array([0.2, 0.3, 0.5]) @ rig.neutral[rig.triangles[t]]
    np.testing.assert_allclose(layout.marker_rig(rig).neutral[0], expected)


def test_bad_layouts(tmp_path, demo):
    rig, _ = demo
    (tmp_path / "m.json").write_text('{"markers": [{"label": "a", "vertex": 999999}]}')
    with pytest.raises(LayoutError, match=r"\['a'\] bound to vertices outside the rig"):
        MarkerLayout.load(tmp_path / "m.json", rig)
    (tmp_path / "m.json").write_text('{"markers": [{"label": "a"}]}')
    with pytest.raises(LayoutError, match="needs 'vertex'"):
        MarkerLayout.load(tmp_path / "m.json", rig)
    (tmp_path / "m.json").write_text("{")
    with pytest.raises(LayoutError, match="m.json"):
        MarkerLayout.load(tmp_path / "m.json", rig)


@pytest.mark.parametrize("text, problem", [
    ('{"markers": [{"label": "a", "vertex": -3}]}', "vertex must be a non-negative integer"),
    ('{"markers": [{"label": "a", "triangle": [1, 2, 3], "barycentric": [1, 0, 0]}]}',
     "triangle must be a non-negative integer"),
    ('{"markers": [{"label": "a", "vertex": 1}, {"label": "a", "vertex": 2}]}', r"\['a'\] appear more than once"),
    ('{"markers": {"a": 1}}', "a \"markers\" list"),
    ('["a"]', "a \"markers\" list"),
    (b"\xff\xfe{", "cannot read marker layout"),
])
def test_hostile_layouts_are_one_error_naming_the_file(tmp_path, demo, text, problem):
    rig, _ = demo
    p = tmp_path / "m.json"
    p.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(LayoutError, match=problem) as err:
        MarkerLayout.load(p, rig)
    assert str(p) in str(err.value)
