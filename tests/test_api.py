"""The Python API (docs/api.md): its page's examples run, its one-liner equals ``livecap solve``, its
errors name the parameter, ``import livecap`` stays cheap."""

from __future__ import annotations

import doctest
import json
import subprocess
import sys

import numpy as np
import pytest

import livecap
from livecap.api.errors import ApiError
from tests.conftest import ROOT
from transport.weights_csv import read_weights_csv

TAKE = ROOT / "recordings" / "demo_take.c3d"
NEUTRAL = ROOT / "recordings" / "demo_neutral.c3d"
RIG = ROOT / "recordings" / "demo_rig.npz"


@pytest.fixture(scope="module")
def profile():
    rig = livecap.load_rig(RIG)
    return livecap.calibrate(livecap.load_take(NEUTRAL), rig, livecap.load_layout(RIG, rig))


def test_api_page_examples_run(monkeypatch):
    monkeypatch.chdir(ROOT)
    result = doctest.testfile(str(ROOT / "docs" / "api.md"), module_relative=False,
                              optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 20 and result.failed == 0


def test_solve_equals_the_commands_csv(tmp_path):
    """The acceptance of issue 38: the one-liner gives ``livecap solve``'s weights, and its CSV its bytes."""
    cli = tmp_path / "cli.csv"
    subprocess.run([sys.executable, "-m", "livecap", "solve", str(TAKE), "--rig", str(RIG), "--out", str(cli)],
                   check=True, capture_output=True, cwd=ROOT)
    weights = livecap.solve(str(TAKE), rig=str(RIG))
    names, values, _ = read_weights_csv(cli)
    assert names == weights.names
    np.testing.assert_allclose(values, weights.values, rtol=0, atol=5.0001e-7)  # the CSV's 6 decimals
    assert weights.to_csv(tmp_path / "api.csv").read_bytes() == cli.read_bytes()


def test_solve_with_a_saved_profile_and_settings_equals_the_command(tmp_path, profile):
    saved = tmp_path / "actor.npz"
    profile.save(saved)
    cli = tmp_path / "cli.csv"
    subprocess.run([sys.executable, "-m", "livecap", "solve", str(TAKE), "--rig", str(RIG), "--profile", str(saved),
                    "--mode", "qp", "--ridge", "0.5", "--out", str(cli)], check=True, capture_output=True, cwd=ROOT)
    weights = livecap.solve(TAKE, rig=RIG, profile=saved, mode="qp", ridge=0.5)
    assert weights.to_csv(tmp_path / "api.csv").read_bytes() == cli.read_bytes()


def test_step_gives_the_live_pipelines_results(profile):
    """Frame by frame, Solver.step publishes what a Session's sinks receive."""
    take = livecap.load_take(TAKE).slice(0, 30)

    class Keep:
        def __init__(self):
            self.results = []

        def publish(self, result):
            self.results.append(result)

        def close(self):
            pass

    sink = Keep()
    livecap.Session(take, livecap.Solver(profile, mode="qp"), [sink]).run()
    solver = livecap.Solver(profile, mode="qp")
    stepped = [solver.step(f) for f in take.select(profile.labels).frames()]
    assert len(sink.results) == len(stepped) == 30
    for a, b in zip(sink.results, stepped, strict=True):
        np.testing.assert_allclose(a.weights, b.weights, atol=1e-12)


def test_a_sink_that_raises_is_counted_not_fatal(profile):
    class Broken:
        def publish(self, result):
            raise RuntimeError("disk full")

        def close(self):
            pass

    stats = livecap.Session(livecap.load_take(TAKE).slice(0, 10), livecap.Solver(profile, mode="lsq"),
                            [Broken()]).run()
    assert stats["frames_out"] == 10 and stats["errors"]["sink_error"] == 10


@pytest.mark.parametrize("call, parameter", [
    (lambda p: livecap.Solver(p, mode="fast"), "mode"),
    (lambda p: livecap.Solver(p, ridg=1.0), "ridg"),
    (lambda p: livecap.Solver("actor.npz"), "profile"),
    (lambda p: livecap.Session([], livecap.Solver(p), [object()]), "sinks[0]"),
    (lambda p: livecap.load_rig(ROOT / "no-such-rig.npz"), "path"),
    (lambda p: livecap.load_take(ROOT / "no-such-take.c3d"), "path"),
    (lambda p: livecap.solve(TAKE, rig=RIG, neutral_seconds=0), "neutral_seconds"),
    (lambda p: livecap.calibrate(livecap.load_take(NEUTRAL), None, None, warp="bendy"), "warp"),
])
def test_errors_name_the_parameter(profile, call, parameter):
    with pytest.raises(ApiError) as err:
        call(profile)
    assert err.value.parameter == parameter and str(err.value).startswith(f"{parameter}: ")


def test_solve_refuses_a_profile_made_for_another_rig_or_markers(profile, tmp_path):
    """As ``livecap solve --profile`` does (issue 35.6): the one-liner checks the profile against ``rig``."""
    from livecap.core.rig import Rig

    rig = Rig.load(RIG)
    other = tmp_path / "other.npz"
    Rig(rig.neutral + np.array([0.0, 0.0, 1.0]), rig.triangles, rig.names, rig.deltas, rig.lower, rig.upper,
        rig.inbetweens, rig.correctives).save(other)
    with pytest.raises(ApiError, match="calibrated against") as err:
        livecap.solve(TAKE, rig=other, profile=profile)
    assert err.value.parameter == "profile" and str(other) in str(err.value)
    layout = tmp_path / "fewer.json"
    data = json.loads(RIG.with_name("demo_rig.markers.json").read_text())
    data["markers"] = data["markers"][:-3]
    layout.write_text(json.dumps(data))
    with pytest.raises(ApiError, match="calibrated with"):
        livecap.solve(TAKE, rig=RIG, profile=profile, markers=layout)


def test_every_public_name_has_a_docstring_and_type_hints():
    import inspect

    for name in livecap.api.__all__:
        obj = getattr(livecap, name)
        assert inspect.getdoc(obj), name
        if inspect.isfunction(obj):
            hints = obj.__annotations__
            assert "return" in hints and all(p in hints for p in inspect.signature(obj).parameters
                                             if p not in ("settings",)), name


def test_import_livecap_loads_no_api():
    """``import livecap`` (what ``livecap --help`` pays) loads neither the API nor numpy; first use does."""
    code = ("import sys, livecap; before = {'livecap.api', 'numpy'} & set(sys.modules); livecap.Weights; "
            "print(sorted(before), 'livecap.api' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True, cwd=ROOT).stdout
    assert out.split() == ["[]", "True"]


def test_glb_is_the_commands(tmp_path):
    """``Weights.to_glb`` writes the bytes of ``livecap solve --out X.glb`` (same file name: the animation is
    named after it)."""
    (tmp_path / "cli").mkdir()
    cli = tmp_path / "cli" / "take.glb"
    subprocess.run([sys.executable, "-m", "livecap", "solve", str(TAKE), "--rig", str(RIG), "--out", str(cli)],
                   check=True, capture_output=True, cwd=ROOT)
    api = livecap.solve(TAKE, rig=RIG).to_glb(tmp_path / "take.glb", livecap.load_rig(RIG))
    assert api.read_bytes() == cli.read_bytes()


def test_the_api_page_and_the_readme_name_the_same_operations():
    """Each command docs/api.md's table gives an API for is in the README's command table, and the README
    points to every API name that table lists (issue 38)."""
    import re

    from tests.test_readme_commands import table_commands

    api_table = [r for r in (ROOT / "docs/api.md").read_text().split("| operation |", 1)[1].split("\n\n", 1)[0]
                 .splitlines() if r.startswith("| ") and not r.startswith("|---")]
    commands = {c for r in api_table for c in re.findall(r"`livecap (\w[\w-]*)", r.split(" | ")[-1])}
    assert commands and commands <= set(table_commands()), commands - set(table_commands())
    readme = (ROOT / "README.md").read_text()
    names = {n for r in api_table for n in re.findall(r"`livecap\.(\w+)", r)}
    assert names and {n for n in names if f"livecap.{n}" not in readme and f"`{n}`" not in readme} == set()
