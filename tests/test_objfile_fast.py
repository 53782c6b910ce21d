"""OBJ reading: numpy's parse of regular files equals the line-by-line reader on any file."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from livecap.core.objfile import _read_lines, _read_regular, read_obj


@settings(max_examples=80, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([3, 4, 5, 0]), st.booleans(), st.booleans(), st.booleans(),
       st.sampled_from(["\n", "\r\n"]))
def test_regular_parse_equals_the_line_reader(tmp_path_factory, seed, size, slashes, extra_coord, negative, eol):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 40))
    lines = ["# a comment", "o mesh"]
    for x, y, z in rng.normal(0, 10, (n, 3)):
        lines.append(f"v {x:.5f} {y:.5f} {z:.5f}" + (" 1.0" if extra_coord else ""))
        lines.append(f"vn {x:.2f} 0 1")
    for _ in range(int(rng.integers(1, 20))):
        k = size or int(rng.integers(3, 6))  # 0: mixed sizes
        idx = rng.integers(1, n + 1, k)
        toks = [str(-(n + 1 - i)) if negative and j == 0 else str(i) for j, i in enumerate(idx)]
        lines.append("f " + " ".join(f"{t}/{t}/{t}" if slashes else t for t in toks))
    text = eol.join(lines) + eol
    path = tmp_path_factory.mktemp("obj") / "m.obj"
    path.write_bytes(text.encode())
    v, f = read_obj(path)
    v0, f0 = _read_lines(path, path.read_text())
    np.testing.assert_array_equal(v, v0)
    np.testing.assert_array_equal(f, f0)
    if size and not (extra_coord or negative) and eol == "\n":
        assert _read_regular(text) is not None  # the common file takes the fast path
