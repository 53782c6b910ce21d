"""LINEAR-key glTF export (issue 37 item 5): players that drop CUBICSPLINE tangents (Blender 3.4)
play these alike; the bound holds at every frame, checked by the Khronos validator and three.js."""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from livecap.review.linear import evaluate_linear, linear_keys
from tests.gltf_validator import TOOL, validate


@settings(max_examples=60, deadline=None)
@given(arrays(np.float64, st.tuples(st.integers(1, 80), st.integers(1, 4)), elements=st.floats(-1, 1)),
       st.floats(1e-4, 0.5))
def test_linear_keys_hold_the_bound_at_every_sample(W, bound):
    times = np.arange(len(W)) / 60.0
    k = linear_keys(times, W, bound)
    assert k[0] == 0 and k[-1] == len(W) - 1 and np.all(np.diff(k) > 0)
    assert np.max(np.abs(evaluate_linear(times[k], W[k], times) - W)) <= bound + 1e-12


def test_a_straight_curve_needs_two_keys():
    times = np.arange(100) / 60.0
    W = np.stack([times, 1 - 2 * times], axis=1)
    assert linear_keys(times, W, 1e-6).tolist() == [0, 99]


def test_linear_glb_plays_within_the_bound_in_three_js(review_server, tmp_path):
    import pygltflib

    status, data = review_server.request("/export/keys-linear.glb?max_error=0.01")
    assert status == 200
    glb = pygltflib.GLTF2.load_from_bytes(data)
    sampler = glb.animations[0].samplers[0]
    assert sampler.interpolation == "LINEAR"
    n_keys = glb.accessors[sampler.input].count
    path = tmp_path / "keys-linear.glb"
    path.write_bytes(data)
    report = validate(path)
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"][:3]
    meta = review_server.request("/api/meta")[1]
    W = np.array(review_server.request("/api/curves")[1]["weights"]).T  # T x m, 5 decimals
    assert 2 <= n_keys <= len(W)  # the test server's per-frame qp solve jitters: ~every frame is a key
    node = shutil.which("node")
    frames = np.arange(0, len(W), 7)
    times = frames / meta["rate"]
    out = subprocess.run([node, str(TOOL / "three_sample.mjs"), str(path), *map(str, times)], capture_output=True,
                         text=True, timeout=120, check=True)
    played = json.loads(out.stdout)
    cols = [played["targets"].index(n) for n in meta["names"]]
    err = np.abs(np.array(played["influences"])[:, cols] - W[frames])
    assert err.max() <= 0.01 + 2e-5  # the bound, plus float32 keys and the curves' 5 decimals
