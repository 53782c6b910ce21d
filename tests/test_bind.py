"""Binding a real capture's markers to a rig (issue 35 item 1): AnimFace takes on ICT and MakeHuman."""

from __future__ import annotations

import functools
import json
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from livecap.calibration.profile import calibrate
from livecap.core.markers import MarkerLayout
from livecap.core.rig import Rig
from livecap.core.take import Take
from livecap.transfer.bind import bind_capture, neutral_span, span_neutral
from livecap.transfer.surface import Surface
from tests.bind_hand_fit import hand_fit
from tests.conftest import ICT, SHARED

ANIMFACE = SHARED / "realdata" / "capture-animface"
MAKEHUMAN = SHARED / "realdata" / "makehuman-head"
TAKES = ["JawMoCap.c3d", "CheeksMoCap.c3d"]

pytestmark = pytest.mark.skipif(not (ANIMFACE.exists() and ICT.exists()),
                                reason=f"real capture or ICT rig absent under {SHARED / 'realdata'}")


@functools.cache
def _ict_rig() -> Rig:
    return Rig.load(ICT)


def _take(name: str) -> Take:
    from transport.takefile import read_take

    return read_take(ANIMFACE / name)


def _scrambled(take: Take, seed: int = 0) -> tuple[Take, list[int]]:
    """Names replaced by meaningless ones, markers shuffled: names must never be required."""
    order = list(np.random.default_rng(seed).permutation(take.n_markers))
    return Take([f"p{i:02d}" for i in range(take.n_markers)], take.positions[:, order], take.valid[:, order],
                take.rate), order


def _points(res, rig: Rig) -> np.ndarray:
    lay = res.layout(rig)
    return lay.sampling_matrix(rig.n_vertices) @ rig.neutral


@pytest.mark.parametrize("name", TAKES)
def test_binding_lands_within_3mm_of_the_hand_fit_with_names_scrambled(ict, name):
    rig, layout = ict
    take = _take(name)
    sites = dict(zip(layout.labels, layout.sampling_matrix(rig.n_vertices) @ rig.neutral, strict=True))
    span = neutral_span(take)
    hand = hand_fit(take.labels, span_neutral(take, span), sites, rig.neutral, rig.triangles)
    named = bind_capture(take, rig, layout)
    assert len(named.anchors) >= 4 and all(m.bound for m in named.markers)
    scrambled, order = _scrambled(take)
    blind = bind_capture(scrambled, rig, layout)
    assert not blind.anchors and all(m.bound for m in blind.markers)
    for res, ref in ((named, hand), (blind, hand[order])):
        err = np.linalg.norm(_points(res, rig) - ref, axis=1)
        assert err.max() < 3.0, err.max()
    # markers on skin: a few mm off the rig's surface, as the hand glue found (2.5 median, 5.5 max)
    dist = np.array([m.distance for m in named.markers])
    assert 0.5 < np.median(dist) < 4.0 and dist.max() < 8.0


@pytest.mark.parametrize("name", TAKES)
def test_stable_set_is_chosen_by_rigidity(ict, name):
    rig, layout = ict
    take = _take(name)
    res = bind_capture(take, rig, layout)
    stable = {m.label for m in res.markers if m.stable}
    assert len(stable) >= 4
    assert {"ForeHead_M", "ForeHead_L", "ForeHead_R"} <= stable
    assert not stable & {"Chin", "Chin_L1", "Chin_R1", "Mouth_Down", "Mouth_Lend", "Mouth_Rend"}
    stab = {m.label: m.stability for m in res.markers}
    assert max(stab[s] for s in stable) < min(stab[c] for c in ("Chin", "Mouth_Down"))


@pytest.mark.parametrize("name", TAKES)
def test_calibration_residual_is_no_worse_than_the_hand_fit(ict, name):
    rig, layout = ict
    take = _take(name)
    res = bind_capture(take, rig, layout)
    neutral = span_neutral(take, res.span)
    auto = calibrate(rig, res.layout(rig), neutral, warp="similarity").settings["warp_fit_rms_mm"]
    sites = dict(zip(layout.labels, layout.sampling_matrix(rig.n_vertices) @ rig.neutral, strict=True))
    hand_pts = hand_fit(take.labels, neutral, sites, rig.neutral, rig.triangles)
    _, tri, bary = Surface(rig.neutral, rig.triangles).closest(hand_pts)
    hand_layout = MarkerLayout(list(take.labels), rig.triangles[tri], bary, np.ones(take.n_markers, bool))
    hand = calibrate(rig, hand_layout, neutral, warp="similarity").settings["warp_fit_rms_mm"]
    assert auto <= hand * 1.02 + 0.01, (auto, hand)


def test_a_marker_off_the_face_is_flagged_not_bound(ict):
    rig, layout = ict
    take = _take("JawMoCap.c3d")
    head = take.labels.index("ForeHead_M")
    band = take.positions[:, head:head + 1] + np.array([0.0, 25.0, 30.0])  # a headband marker in front of the brow
    t2 = Take(take.labels + ["Band"], np.concatenate([take.positions, band], axis=1),
              np.concatenate([take.valid, take.valid[:, head:head + 1]], axis=1), take.rate)
    res = bind_capture(t2, rig, layout)
    flagged = {m.label: m.reason for m in res.markers if not m.bound}
    assert list(flagged) == ["Band"] and "mm" in flagged["Band"]
    assert "Band" not in res.layout(rig).labels


@pytest.mark.skipif(not MAKEHUMAN.exists(), reason=f"MakeHuman head absent: {MAKEHUMAN}")
def test_binds_to_the_makehuman_head_without_landmarks():
    rig = Rig.load(MAKEHUMAN)
    res = bind_capture(_take("JawMoCap.c3d"), rig, None)
    bound = [m for m in res.markers if m.bound]
    assert len(bound) >= 35 and not res.anchors
    assert np.median([m.distance for m in bound]) < 4.0
    assert 0.8 < res.alignment.scale < 1.2


def test_cli_writes_a_layout_that_calibration_reads(tmp_path):
    out = tmp_path / "markers.json"
    proc = subprocess.run([sys.executable, "-m", "livecap", "markers", "bind", str(ANIMFACE / "CheeksMoCap.c3d"),
                           "--rig", str(ICT), "--out", str(out), "--span", "0.5:1.2"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "neutral span 0.50-1.20 s" in proc.stdout and "Mouth_Lend" in proc.stdout
    data = json.loads(out.read_text())
    assert all("triangle" in m and "distance_mm" in m for m in data["markers"])
    rig = _ict_rig()
    lay = MarkerLayout.load(out, rig)
    assert lay.n_markers == 41 and 4 <= lay.stable.sum() < 20
    bad = subprocess.run([sys.executable, "-m", "livecap", "markers", "bind", str(ANIMFACE / "CheeksMoCap.c3d"),
                          "--rig", str(ICT), "--out", str(out), "--span", "20:99"],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 1 and bad.stderr.count("\n") == 1 and "--span" in bad.stderr


def test_stable_set_sees_through_white_marker_noise():
    """The demo take: 0.5 mm white noise on every marker (59 of 60 were 'stable' before the noise was taken out
    of the pairwise spreads); the rig's own stable markers are found, no lip, chin or jaw marker is."""
    from livecap.transfer.bind import stability
    from tests.conftest import ROOT
    from transport.takefile import read_take

    take = read_take(ROOT / "recordings" / "demo_take.c3d")
    _, stable = stability(take, span_neutral(take, neutral_span(take)))
    chosen = {lab for lab, s in zip(take.labels, stable, strict=True) if s}
    truth = {m["label"] for m in json.loads((ROOT / "recordings" / "demo_rig.markers.json").read_text())["markers"]
             if m["stable"]}
    assert truth <= chosen and len(chosen) < 30
    assert not {lab for lab in chosen if lab.startswith(("LIP", "CORNER", "CHIN", "JAW", "MTH"))}


@settings(max_examples=4, deadline=None)
@given(axis=st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda v: np.linalg.norm(v) > 0.1),
       degrees=st.floats(-5, 5), shift=st.tuples(*[st.floats(-300, 300)] * 3))
def test_binding_does_not_depend_on_where_the_capture_volume_puts_the_head(axis, degrees, shift):
    """Invariant: a rigid move of the whole capture (a few degrees, any shift) binds to the same sites."""
    from scipy.spatial.transform import Rotation

    rig = _ict_rig()
    take = _take("JawMoCap.c3d")
    R = Rotation.from_rotvec(np.radians(degrees) * np.asarray(axis) / np.linalg.norm(axis)).as_matrix()
    moved = Take(take.labels, take.positions @ R.T + np.asarray(shift), take.valid, take.rate)
    a, b = bind_capture(take, rig), bind_capture(moved, rig)
    assert np.linalg.norm(_points(a, rig) - _points(b, rig), axis=1).max() < 0.5
    assert [m.stable for m in a.markers] == [m.stable for m in b.markers]


def test_a_range_of_motion_take_is_where_rigidity_is_measured(ict):
    from livecap.transfer.bind import BindError, stability

    rig, layout = ict
    jaw, cheeks = _take("JawMoCap.c3d"), _take("CheeksMoCap.c3d")
    res = bind_capture(jaw, rig, layout, rom=cheeks)
    _, expect = stability(cheeks.select(jaw.labels), span_neutral(jaw, res.span))
    assert [m.stable for m in res.markers] == list(expect)
    assert [m.stable for m in res.markers] != [m.stable for m in bind_capture(jaw, rig, layout).markers]
    with pytest.raises(BindError, match="lacks markers"):
        bind_capture(jaw, rig, layout, rom=cheeks.select(cheeks.labels[:-1]))


@pytest.mark.parametrize("suffix", ["glb", "usda"])
def test_cli_binds_to_every_rig_format_load_rig_reads(tmp_path, ict, suffix):
    """The ICT rig written as a GLB (a decoy body mesh, a turned and halved parent node) and as USD (Z-up,
    centimetres) by third-party writers: ``markers bind --rig FILE`` reads it (the markers.json beside it as
    ``<rig>.markers.json`` gives the landmarks) and binds the markers where the OBJ folder's rig puts them."""
    from tests.rig_writers import read_obj_rig, write_gltf, write_usd

    rig, layout = ict
    src = read_obj_rig(ICT, ["jawOpen"], 0.01)
    path = (write_gltf(tmp_path / "ict.glb", src) if suffix == "glb"
            else write_usd(tmp_path / "ict.usda", src))
    (tmp_path / "ict.markers.json").write_text((ICT / "markers.json").read_text())
    out = tmp_path / "bound.json"
    proc = subprocess.run([sys.executable, "-m", "livecap", "markers", "bind", str(ANIMFACE / "JawMoCap.c3d"),
                           "--rig", str(path), "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "9 name hints" in proc.stdout
    ref = bind_capture(_take("JawMoCap.c3d"), rig, layout)
    got = MarkerLayout.load(out, rig)
    assert got.labels == [m.label for m in ref.markers if m.bound]
    assert np.linalg.norm(got.sampling_matrix(rig.n_vertices) @ rig.neutral - _points(ref, rig), axis=1).max() < 0.05


@pytest.mark.skipif(not MAKEHUMAN.exists(), reason=f"MakeHuman head absent: {MAKEHUMAN}")
def test_binding_against_the_true_anatomy_of_another_face(ict):
    """Where truth exists: the MakeHuman head wears ICT's own 60 sites (on its anatomy by the rig transfer since
    2026-12-05, ±2 mm, 2-5 mm off the skin, livecap.demo.mismatch_take), so the distance from each bound site to its
    true ICT site is the binding's error on a face whose proportions are not the rig's. Measured 2026-12-04 with the
    old sites: median 4.3 mm, max 9.1 mm; 2026-12-05 on the 10 s realeval takes: 4.1 / 10.7 mm (docs/robustness.md;
    the issue's 3 mm is not met): a guard against getting worse, not the goal."""
    from livecap.demo.mismatch_take import MismatchSettings, mismatch_take
    from tests.conftest import ROOT
    from transport.arkit import load_mapping

    rig, layout = ict
    mt = mismatch_take(Rig.load(MAKEHUMAN), rig, layout, SHARED / "realdata" / "performance" / "S07-001.csv",
                       load_mapping(ROOT / "examples" / "makehuman_arkit.json"), MismatchSettings(seconds=2.0))
    true = dict(zip(layout.labels, layout.sampling_matrix(rig.n_vertices) @ rig.neutral, strict=True))
    err = np.linalg.norm(mt.layout.sampling_matrix(rig.n_vertices) @ rig.neutral
                         - np.array([true[lab] for lab in mt.layout.labels]), axis=1)
    assert mt.layout.n_markers == 60
    assert np.median(err) < 5.0 and err.max() < 10.0, (np.median(err), err.max())
