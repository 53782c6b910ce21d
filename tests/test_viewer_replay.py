"""``livecap replay`` in a real subprocess: an MP4 OpenCV can open, with the right frames and size."""

from __future__ import annotations

import subprocess
import sys

import cv2
import numpy as np
import pytest

from livecap.demo import truth_path
from livecap.demo.performance import PerformanceSettings, perform
from transport.takefile import write_take


@pytest.fixture(scope="module")
def short_take(tmp_path_factory, demo):
    rig, layout = demo
    folder = tmp_path_factory.mktemp("replay")
    rig.save(folder / "rig.npz")
    layout.save(folder / "rig.markers.json")
    perf = perform(rig, layout, PerformanceSettings(seconds=1.5, rate=24.0, seed=5, occlusion=0.0, stable_dropout=0.0))
    write_take(perf.take, folder / "take.c3d")
    perf.save_truth(truth_path(folder / "take.c3d"))
    return folder, perf.take.n_frames


def _replay(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "livecap", "replay", *args], capture_output=True, text=True,
                          timeout=240)


def _read_video(path) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(path))
    assert cap.isOpened()
    frames = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        frames.append(img)
    cap.release()
    return frames


def test_replay_writes_side_by_side_mp4_and_pngs(short_take):
    folder, n_frames = short_take
    out, pngs = folder / "out.mp4", folder / "frames"
    proc = _replay(str(folder / "take.c3d"), "--rig", str(folder / "rig.npz"), "--preview", str(out),
                   "--frames", str(pngs), "--size", "240x180", "--every", "3", "--msaa", "0")
    assert proc.returncode == 0, proc.stderr
    expected = len(range(0, n_frames, 3))
    import av  # the encoder's own package probes what was written: H.264 in yuv420p, browser-playable

    with av.open(str(out)) as probe:
        video = probe.streams.video[0]
        assert (video.codec_context.name, video.codec_context.pix_fmt) == ("h264", "yuv420p")
        assert probe.format.name.startswith("mov,mp4")
    cap = cv2.VideoCapture(str(out))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == expected
    assert (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))) == (480, 180)
    cap.release()
    frames = _read_video(out)
    assert len(frames) == expected and frames[0].shape == (180, 480, 3)  # truth | solved, 240 wide each
    files = sorted(pngs.glob("frame_*.png"))
    assert [f.name for f in files][:2] == ["frame_000000.png", "frame_000003.png"] and len(files) == expected
    png = cv2.imread(str(files[-1]))
    assert png.shape == (180, 480, 3)
    for half in (png[:, :240], png[:, 240:]):  # a face in each panel: bright pixels around the centre
        assert (half[40:140, 70:170].max(axis=2) > 150).mean() > 0.3
    assert "ground truth on the left" in proc.stdout


def test_replay_without_truth_and_bad_input(short_take, tmp_path):
    folder, n_frames = short_take
    out = tmp_path / "solo.mp4"
    proc = _replay(str(folder / "take.c3d"), "--rig", str(folder / "rig.npz"), "--preview", str(out),
                   "--size", "200x150", "--every", "4", "--no-truth", "--msaa", "0")
    assert proc.returncode == 0, proc.stderr
    frames = _read_video(out)
    assert len(frames) == len(range(0, n_frames, 4)) and frames[0].shape == (150, 200, 3)
    bad = _replay(str(folder / "take.c3d"), "--rig", str(folder / "rig.npz"))
    assert bad.returncode != 0 and "--preview" in bad.stderr and "Traceback" not in bad.stderr
