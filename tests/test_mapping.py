"""Weight mapping between parameterisations (Lewis et al. 2014 §5.3)."""

from __future__ import annotations

import numpy as np
import pytest

from livecap.mapping import MappingError, by_name, cloning_matrix, load_config


def test_gain_offset_clamp_and_identity_by_name(tmp_path):
    cfg = tmp_path / "map.toml"
    cfg.write_text('[defaults]\nclamp = [0.0, 1.0]\n[channels.jawOpen]\nsource = "JawOpen"\ngain = 2.0\n'
                   'offset = 0.1\n[channels.smile]\ngain = -1.0\nclamp = [-0.5, 0.5]\n')
    m = by_name(["JawOpen", "smile", "blink"], ["jawOpen", "smile", "blink", "tongueOut"], load_config(cfg))
    out = m.apply(np.array([[0.2, 0.8, 0.3], [0.7, -0.2, 1.4]]))
    np.testing.assert_allclose(out, [[0.5, -0.5, 0.3, 0.0], [1.0, 0.2, 1.0, 0.0]])
    assert m.unmapped == ["tongueOut"]
    np.testing.assert_allclose(m.apply(np.array([0.2, 0.8, 0.3])), out[0])


def test_json_config_and_errors(tmp_path):
    cfg = tmp_path / "map.json"
    cfg.write_text('{"channels": {"a": {"gain": 0.5}}}')
    np.testing.assert_allclose(by_name(["a"], ["a"], load_config(cfg)).apply(np.array([1.0])), [0.5])
    with pytest.raises(MappingError, match="lacks"):
        by_name(["a"], ["a"], {"channels": {"zz": {}}})
    with pytest.raises(MappingError, match="not a source"):
        by_name(["a"], ["a"], {"channels": {"a": {"source": "nope"}}})
    with pytest.raises(MappingError, match="map.json"):
        (tmp_path / "map.json").write_text("{broken")
        load_config(tmp_path / "map.json")


def test_cloning_matrix_recovers_a_linear_map():
    rng = np.random.default_rng(0)
    E = rng.normal(0, 1, (7, 5))
    W = rng.uniform(0, 1, (20, 5))
    np.testing.assert_allclose(cloning_matrix(W, W @ E.T), E, atol=1e-10)
    with pytest.raises(MappingError, match="at least"):
        cloning_matrix(W[:3], (W @ E.T)[:3])
    assert cloning_matrix(W[:3], (W @ E.T)[:3], ridge=1e-3).shape == (7, 5)
