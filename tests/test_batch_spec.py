"""A batch job's typed settings (livecap.batch.spec) mean what the same flags mean to ``livecap solve``: any
flags give the options the command builds its solver from (cli/solve.solve_options) and its noise; bad
flags fail on the client with a line naming the flag; a spec is checked when made."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from livecap.batch.spec import SolveSettings, SolveSpec
from livecap.cli import build_parser
from livecap.cli.batch import JOB_FLAGS, settings_from_flags
from livecap.cli.solve import solve_options

BASE = ["take.c3d", "--rig", "rig.npz", "--out", "out.csv"]


def _solve_parser():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    return sub.choices["solve"]


def _number(kind):
    if kind is int:
        return st.integers(-5, 500).map(str)
    return st.one_of(st.floats(-1e3, 1e3, allow_nan=False).map(repr), st.sampled_from(["0", "1e-3", "2", "-0.5"]))


def _flag(action):
    flag = action.option_strings[-1]
    if action.nargs == 0:  # a switch
        return st.just([flag])
    if action.choices:
        value = st.sampled_from(list(action.choices))
    elif action.dest == "noise_mm":
        value = st.floats(0.01, 10).map(repr)
    elif action.type in (int, float):
        value = _number(action.type)
    elif action.dest == "prior":
        value = st.sampled_from(["none", "shapes", "profile", "prior.npz", "dir/p.npz"])
    elif action.dest == "marker_weight":
        value = st.tuples(st.sampled_from(["lip*", "chin", "a=b", "L1"]), _number(float)).map("=".join)
    else:
        value = st.sampled_from(["keys.json", "dir/k.json"])
    return value.flatmap(lambda v: st.sampled_from([[flag, v], [f"{flag}={v}"]]))


SETTING_ACTIONS = [a for a in _solve_parser()._actions
                   if a.option_strings and not set(a.option_strings) & set(JOB_FLAGS)]
FLAGS = st.lists(st.one_of([_flag(a) for a in SETTING_ACTIONS]), max_size=12).map(lambda xs: sum(xs, []))


def test_every_solve_flag_is_a_setting_or_a_job_column():
    """A new ``livecap solve`` flag must land in SolveSettings (or be declared a job's own)."""
    dests = {a.dest for a in SETTING_ACTIONS} - {"marker_weight"}
    assert dests == {f for f in SolveSettings.__dataclass_fields__} - {"marker_weights"}


@settings(max_examples=150, deadline=None)
@given(FLAGS)
def test_any_flags_give_the_settings_of_livecap_solve(flags):
    """Equal options, or both refuse the flags (argparse reads '-5e-3' as a flag, not a negative value)."""
    try:
        args = _solve_parser().parse_args(BASE + flags)
    except SystemExit:
        with pytest.raises(ValueError, match="solve options: "):
            settings_from_flags(flags)
        return
    typed = settings_from_flags(flags)
    assert typed.options() == solve_options(args)
    assert typed.noise_mm == args.noise_mm


def test_a_weights_csv_prior_is_read_as_the_command_reads_it(tmp_path):
    path = tmp_path / "prior.csv"
    path.write_text("frame,time,jawOpen,smile\n0,0.0,0.1,0.2\n1,0.01,0.3,0.4\n")
    flags = ["--prior", str(path), "--alpha", "0.5"]
    ours, theirs = settings_from_flags(flags).options(), solve_options(_solve_parser().parse_args(BASE + flags))
    assert ours.pop("prior")["names"] == theirs["prior"]["names"]
    np.testing.assert_array_equal(theirs.pop("prior")["weights"], np.asarray([[0.1, 0.2], [0.3, 0.4]]))
    assert ours == {k: v for k, v in theirs.items() if k != "prior"}


@pytest.mark.parametrize("flags, message", [
    ("--no-such-flag", "unrecognized arguments: --no-such-flag"), ("--ridge", "argument --ridge: expected one"),
    ("--ridge x", "argument --ridge: invalid float value: 'x'"), ("--limits hard", "argument --limits: invalid choice"),
    ("--window 2.5", "argument --window: invalid int value"), ("--plain=1", "argument --plain"),
    ("--trend", "argument --trend: expected one"), ("--neutral 2", "unrecognized arguments: --neutral"),
    ("--mode qp", "--mode is not a solver setting"), ("--profile=p.npz", "--profile is not a solver setting"),
    ("--unlabelled", "label the takes first"), ("--marker-weight lip", "--marker-weight 'lip': expected LABEL=WEIGHT"),
    ("--noise-mm 0", "noise_mm must be positive"), ("--help", "--help is not a solver setting"),
])
def test_bad_flags_name_the_flag_on_one_line(flags, message):
    with pytest.raises(ValueError, match=message) as info:
        settings_from_flags(flags.split())
    assert "\n" not in str(info.value)


def test_a_spec_is_checked_when_made():
    with pytest.raises(ValueError, match="mode: unknown solver mode 'fast'"):
        SolveSpec("rig.npz", "fast")
    with pytest.raises(ValueError, match="needs key pairs"):
        SolveSpec("rig.npz", "rbf")
    with pytest.raises(ValueError, match="limits: 'hard' is not one of none, clip, bound"):
        SolveSettings(limits="hard")
    spec = SolveSpec("rig.npz", "qp", settings=SolveSettings(ridge=1.0, marker_weights=(("lip*", 2.0),)))
    assert hash(spec) == hash(SolveSpec("rig.npz", "qp", settings=SolveSettings(ridge=1.0,
                                                                                  marker_weights=(("lip*", 2.0),))))


def test_the_progress_bar_redraws_twice_a_second_not_ten_times():
    """rich's default of 10 redraws a second costs the `livecap batch` process ~11 ms CPU a second in a terminal, on
    the cores the workers solve on (docs/batch.md "the wall beyond CPU")."""
    from livecap.cli.batch import _progress

    prog, done = _progress(3)
    assert prog.live.refresh_per_second == 2 and prog.live.auto_refresh
    done({"status": "ok", "frames": 10, "take": "a"})
    assert prog.tasks[0].completed == 1
