"""Actor basis from a range-of-motion take (Curio et al. 2006 §2.3)."""

from __future__ import annotations

import numpy as np
import pytest

from livecap.calibration.actor_basis import actor_basis
from livecap.calibration.keys import KeySpec, keys_from_take, load_keys, read_key_file, write_key_file
from livecap.calibration.profile import calibrate
from livecap.demo.performance import PerformanceSettings
from livecap.demo.rom import rom_take


@pytest.fixture(scope="module")
def rom(demo):
    rig, layout = demo
    shapes = ["jawOpen", "mouthSmileLeft", "mouthSmileRight", "browInnerUp", "eyeBlinkLeft", "mouthFunnel"]
    perf, specs = rom_take(rig, layout, PerformanceSettings(rate=60, noise_mm=0.0, occlusion=0.0, seed=4),
                           shapes=shapes)
    return rig, layout, perf, specs + [KeySpec("notAShape", start=specs[0].start, end=specs[0].end)]


def test_peak_frames_make_the_actor_basis(rom):
    rig, layout, perf, specs = rom
    profile = calibrate(rig, layout, perf.actor_neutral)
    keys = keys_from_take(perf.take, profile, specs)
    assert keys.skipped == ["notAShape"]
    actor, report = actor_basis(profile, keys)
    assert report.unmatched_keys == ["notAShape"]
    assert sorted(report.from_actor) == sorted(s.name for s in specs[:-1])
    assert set(report.no_actor_pose) == set(rig.names) - set(report.from_actor)
    assert any("no actor pose" in line for line in report.lines())
    # the actor's own motion: the warped actor markers at full weight, in the stabilised frame
    k = rig.index("jawOpen")
    w = np.zeros(rig.n_shapes)
    w[k] = 1.0
    frame = keys.frames[keys.names.index("jawOpen")]
    stab = keys.source[keys.names.index("jawOpen")].reshape(-1)
    np.testing.assert_allclose(actor.basis[:, k], stab)
    assert perf.weights[frame, k] == pytest.approx(1.0)
    # it is the actor's own motion (noise-free take): closer than the similarity-warped rig column
    from livecap.demo.performance import actor_warp

    warp = actor_warp(np.random.default_rng(perf.settings.actor_seed))
    sites = layout.marker_rig(rig)
    truth = (warp(sites.evaluate(w)) - warp(sites.neutral)).reshape(-1)
    actor_err = np.abs(actor.basis[:, k] - truth).max()
    rig_err = np.abs(profile.basis[:, k] - truth).max()
    assert actor_err < 0.05 and actor_err < 0.2 * rig_err
    untouched = rig.index(report.no_actor_pose[0])
    np.testing.assert_array_equal(actor.basis[:, untouched], profile.basis[:, untouched])
    dropped, _ = actor_basis(profile, keys, missing="drop")
    assert dropped.upper[untouched] == 0 and not dropped.basis[:, untouched].any()


def test_keys_file_round_trip_and_qp_actor_mode(rom, tmp_path):
    from livecap.modes.registry import build_solver
    from transport.takefile import write_take

    rig, layout, perf, specs = rom
    write_take(perf.take, tmp_path / "rom.c3d")
    write_key_file(tmp_path / "rom.keys.json", specs, take="rom.c3d")
    take_path, read_specs = read_key_file(tmp_path / "rom.keys.json")
    assert take_path == tmp_path / "rom.c3d" and read_specs == specs
    profile = calibrate(rig, layout, perf.actor_neutral)
    keys = load_keys(tmp_path / "rom.keys.json", profile)
    solver = build_solver("qp", profile, {"basis": "actor", "keys": str(tmp_path / "rom.keys.json")})
    k = keys.names.index("mouthFunnel")
    w = solver.step(keys.source[k], np.ones(layout.n_markers, bool))
    assert w[rig.index("mouthFunnel")] == pytest.approx(1.0, abs=1e-6)
    with pytest.raises(ValueError, match="needs keys"):
        build_solver("qp", profile, {"basis": "actor"})


def test_bad_key_files(tmp_path):
    from livecap.calibration.keys import KeyFileError

    p = tmp_path / "k.json"
    p.write_text('{"keys": [{"name": "a"}]}')
    with pytest.raises(KeyFileError, match="needs 'frame'"):
        read_key_file(p)
    p.write_text("not json")
    with pytest.raises(KeyFileError, match="k.json"):
        read_key_file(p)
