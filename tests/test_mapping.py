"""Weight mapping between parameterisations (Lewis et al. 2014 §5.3)."""

from __future__ import annotations

import numpy as np
import pytest

from livecap.offline.mapping import MappingError, by_name, cloning_matrix, load_config


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


def test_map_command_by_name_and_by_pairs(tmp_path):
    from livecap.cli import main
    from transport.weights_csv import read_weights_csv, write_weights_csv

    W = np.array([[0.2, 0.9], [0.6, 0.1], [1.0, 0.5]])
    write_weights_csv(tmp_path / "w.csv", ["jaw", "smile"], W, 120.0)
    (tmp_path / "m.json").write_text('{"channels": {"smile": {"gain": 2, "clamp": [0, 1]}}}')
    assert main(["map", str(tmp_path / "w.csv"), "--config", str(tmp_path / "m.json"),
                 "--out", str(tmp_path / "o.csv")]) == 0
    names, V, _ = read_weights_csv(tmp_path / "o.csv")
    assert names == ["jaw", "smile"]
    np.testing.assert_allclose(V, [[0.2, 1.0], [0.6, 0.2], [1.0, 1.0]])
    E = np.array([[1.0, 0.5], [0.0, 2.0], [0.3, 0.3]])
    write_weights_csv(tmp_path / "src.csv", ["jaw", "smile"], W, 1.0)
    write_weights_csv(tmp_path / "tgt.csv", ["a", "b", "c"], W @ E.T, 1.0)
    assert main(["map", str(tmp_path / "w.csv"), "--pairs", str(tmp_path / "src.csv"), str(tmp_path / "tgt.csv"),
                 "--out", str(tmp_path / "o2.csv")]) == 0
    names, V, _ = read_weights_csv(tmp_path / "o2.csv")
    assert names == ["a", "b", "c"]
    np.testing.assert_allclose(V, W @ E.T, atol=1e-5)
