"""One name matcher (livecap.core.names) for livecap map, the ARKit sinks and anything that pairs names."""

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from livecap.core.names import match_names, name_key
from transport.arkit import ARKIT_NAMES, arkit_matrix


@given(st.sampled_from(ARKIT_NAMES), st.sampled_from(["_", ".", "-", ""]), st.booleans())
def test_spellings_of_one_shape_share_a_key(name, sep, upper):
    stem = name.removesuffix("Left").removesuffix("Right")
    side = name[len(stem):]
    spelled = stem + (sep + side[0] if side and sep else side)
    spelled = spelled[0].upper() + spelled[1:] if upper else spelled
    assert name_key(spelled) == name_key(name)


def test_sides_case_and_mean_of_sides():
    m = match_names(["EyeBlinkLeft", "eye_blink.r", "browInnerUp_L", "browInnerUp_R", "jaw"],
                    ["eyeBlink_L", "eyeBlinkRight", "browInnerUp", "jawLeft", "tongueOut"])
    assert m.sources == ((0,), (1,), (2, 3), (), ())  # "jawLeft" is a shape of its own, not "jaw"'s left side
    assert m.unmatched == ["jawLeft", "tongueOut"] and m.unused == ["jaw"]
    np.testing.assert_allclose(m.matrix()[2], [0, 0, 0.5, 0.5, 0])
    assert match_names(["browInnerUp"], ["browInnerUp_L"]).sources == ((0,),)  # side-less source fans out
    assert match_names(["a", "A"], ["A"]).sources == ((1,),)  # an exact name wins


def test_live_link_mapping_is_the_shared_matcher():
    names = ["eyeBlink_L", "eyeBlink_R", "browInnerUp_L", "browInnerUp_R", "JawOpen"]
    np.testing.assert_array_equal(arkit_matrix(names), match_names(names, ARKIT_NAMES).matrix())


def _rig(path, names):
    from livecap.core.rig import Rig

    rng = np.random.default_rng(0)
    Rig(rng.normal(size=(4, 3)), np.array([[0, 1, 2]]), names, rng.normal(size=(len(names), 4, 3))).save(path)
    return path


def test_map_to_a_rig_with_other_spellings(tmp_path, capsys):
    """Finding 3 (issue 21): ARKit-named weights onto an ICT-style rig map by the shared matcher."""
    from livecap.cli import main
    from transport.weights_csv import read_weights_csv, write_weights_csv

    W = np.array([[0.1, 0.7, 0.3], [0.4, 0.2, 0.9]])
    write_weights_csv(tmp_path / "w.csv", ["eyeBlinkLeft", "eyeBlinkRight", "jawOpen"], W, 120.0)
    target = _rig(tmp_path / "t.npz", ["eyeBlink_L", "eyeBlink_R", "jawOpen", "tongueOut"])
    assert main(["map", str(tmp_path / "w.csv"), "--target-rig", str(target), "--out", str(tmp_path / "o.csv")]) == 0
    names, V, _ = read_weights_csv(tmp_path / "o.csv")
    np.testing.assert_allclose(V[:, :3], W)
    assert "matched 3 of 4" in capsys.readouterr().out


def test_map_with_most_channels_unmatched_fails_with_a_hint(tmp_path, capsys):
    from livecap.cli import main
    from transport.weights_csv import write_weights_csv

    write_weights_csv(tmp_path / "w.csv", ["jawOpen"], np.zeros((2, 1)), 120.0)
    target = _rig(tmp_path / "t.npz", ["JawDrop", "LipPucker", "jawOpen"])
    out = tmp_path / "o.csv"
    assert main(["map", str(tmp_path / "w.csv"), "--target-rig", str(target), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "2 of 3 target channels have no source" in err and "--config" in err and not out.exists()
    assert main(["map", str(tmp_path / "w.csv"), "--target-rig", str(target), "--out", str(out),
                 "--allow-unmatched"]) == 0 and out.exists()
