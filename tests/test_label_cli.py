"""``livecap label`` and ``livecap solve --unlabelled`` on a C3D file of unnamed, shuffled points."""

import numpy as np
import pytest

from livecap.calibration.profile import calibrate, estimate_neutral
from livecap.cli import main
from livecap.demo.unlabelled import scramble
from transport.takefile import read_take, write_take
from transport.weights_csv import read_weights_csv


@pytest.fixture(scope="module")
def files(demo, tmp_path_factory):
    from livecap.demo.performance import PerformanceSettings, perform

    rig, layout = demo
    d = tmp_path_factory.mktemp("label")
    perf = perform(rig, layout, PerformanceSettings(seconds=3.0, seed=8))
    take = perf.take.select(layout.labels)
    profile = calibrate(rig, layout, estimate_neutral(take, layout.stable, 120))
    profile.save(d / "p.npz")
    rig.save(d / "rig.npz")
    layout.save(d / "rig.markers.json")
    sc = scramble(take, seed=2)
    write_take(sc.cloud, d / "cloud.c3d")
    write_take(sc.occluded, d / "labelled_truth.c3d")
    return d, sc, perf.weights


def test_label_writes_the_labelled_take(files, capsys):
    d, sc, _ = files
    assert main(["label", str(d / "cloud.c3d"), "--profile", str(d / "p.npz"), "--out", str(d / "out.c3d")]) == 0
    assert "track start" in capsys.readouterr().out
    out = read_take(d / "out.c3d")
    truth = sc.occluded
    assert out.labels == truth.labels
    both = out.valid & truth.valid
    assert both.sum() >= 0.995 * truth.valid.sum()
    right = np.linalg.norm(out.positions - truth.positions, axis=-1)[both] < 1e-3
    assert right.mean() >= 0.995


def test_solve_unlabelled_matches_the_labelled_solve(files):
    d, _, truth = files
    common = ["--rig", str(d / "rig.npz"), "--profile", str(d / "p.npz"), "--mode", "qp"]
    assert main(["solve", str(d / "cloud.c3d"), "--unlabelled", *common, "--out", str(d / "u.csv")]) == 0
    assert main(["solve", str(d / "labelled_truth.c3d"), *common, "--out", str(d / "l.csv")]) == 0
    (_, u, _), (_, lab, _) = read_weights_csv(d / "u.csv"), read_weights_csv(d / "l.csv")
    assert u.shape == lab.shape
    assert np.sqrt(np.mean((u - truth) ** 2)) <= 1.05 * np.sqrt(np.mean((lab - truth) ** 2))


def test_label_needs_a_profile(files, capsys):
    d, _, _ = files
    assert main(["solve", str(d / "cloud.c3d"), "--unlabelled", "--rig", str(d / "rig.npz"), "--out",
                 str(d / "x.csv")]) == 1
    assert "--unlabelled needs --profile" in capsys.readouterr().err
