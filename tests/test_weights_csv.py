"""Weight curves CSV (transport/weights_csv.py): byte for byte what ``csv.writer`` and Python's ``.6f`` write."""

from __future__ import annotations

import csv
import io

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from transport.fixed_point import format_rows
from transport.weights_csv import read_weights_csv, write_weights_csv


def _reference(names, W, rate, first):
    out = io.StringIO()
    w = csv.writer(out)
    w.writerow(["frame", "time", *names])
    for i, row in enumerate(np.asarray(W).tolist()):
        out.write(",".join([f"{first + i:d}", f"{i / rate:.6f}"] + [f"{v:.6f}" for v in row]) + "\r\n")
    return out.getvalue().encode("utf-8")


floats = st.one_of(
    st.floats(-2.0, 2.0),
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-3_000_000, 3_000_000).map(lambda k: k / 1e6 + 5e-7),  # a hair from half-way, or on it
    st.integers(-3_000_000, 3_000_000).map(lambda k: (k + 0.5) / 1e6),
    st.sampled_from([0.0, -0.0, -1e-9, -4.9e-7, 5e-7, 999_999_999.9999995, 1e9, -1e9, 1e300, 5e-324]),
)


@settings(max_examples=300, deadline=None)
@given(values=st.lists(floats, min_size=1, max_size=24), rate=st.sampled_from([60.0, 119.88, 120.0, 7.0]),
       first=st.integers(-5, 10**12))
def test_bytes_equal_percent_formatting(tmp_path_factory, values, rate, first):
    m = 3
    W = np.resize(np.array(values, dtype=np.float64), (max(1, len(values) // m), m))
    names = ["jawOpen", "eyeBlink_L", "mouthSmile é"]
    path = tmp_path_factory.mktemp("csv") / "w.csv"
    write_weights_csv(path, names, W, rate, first)
    assert path.read_bytes() == _reference(names, W, rate, first)


def test_the_kernel_takes_ordinary_values_and_hands_back_doubtful_ones():
    rng = np.random.default_rng(0)
    W = rng.uniform(-1, 1.5, (50, 7))
    buf = np.empty(50 * (21 + 19 * 8 + 2), np.uint8)
    n = format_rows(np.arange(50, dtype=np.int64), np.arange(50) / 120.0, W, buf)
    assert n > 0 and buf[:n].tobytes() == _reference([], W, 120.0, 0).split(b"\r\n", 1)[1]
    for doubtful in (np.nan, np.inf, 2e9, 0.0000005):
        W[3, 2] = doubtful
        assert format_rows(np.arange(50, dtype=np.int64), np.arange(50) / 120.0, W, buf) == -1


def test_round_trip(tmp_path):
    W = np.random.default_rng(1).uniform(0, 1, (300, 5))
    write_weights_csv(tmp_path / "w.csv", list("abcde"), W, 60.0, 10)
    names, back, times = read_weights_csv(tmp_path / "w.csv")
    assert names == list("abcde") and np.abs(back - W).max() <= 5e-7
    assert np.abs(times - np.arange(300) / 60).max() <= 5e-7
