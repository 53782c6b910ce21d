import struct
import warnings

import numpy as np
import pytest

from livecap.core.take import Take
from transport.c3d_check import Param, _int
from transport.errors import TakeFileError
from transport.takefile import read_take, write_take


def random_take(n_frames=50, n=5, seed=0):
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-500, 500, (n_frames, n, 3))
    valid = rng.random((n_frames, n)) > 0.1
    return Take([f"m{i}" for i in range(n)], pos, valid, 120.0)


@pytest.mark.parametrize("ext", [".c3d", ".trc", ".csv"])
def test_round_trip(tmp_path, ext):
    take = random_take()
    write_take(take, tmp_path / f"t{ext}")
    back = read_take(tmp_path / f"t{ext}")
    assert back.labels == take.labels and back.rate == take.rate
    np.testing.assert_array_equal(back.valid, take.valid)
    np.testing.assert_allclose(back.positions, take.positions, atol=1e-3)


def test_c3d_read_by_independent_reader(tmp_path):
    import c3d  # the pure-Python 'c3d' package, not ezc3d

    take = random_take(n_frames=20, n=4, seed=2)
    write_take(take, tmp_path / "t.c3d")
    with open(tmp_path / "t.c3d", "rb") as fh, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = c3d.Reader(fh)
        assert r.point_rate == 120.0
        assert [s.strip() for s in r.point_labels] == take.labels
        assert r.get("POINT:UNITS").string_value.strip() == "mm"
        frames = [pts for _, pts, _ in r.read_frames()]
    pts = np.stack(frames)
    assert pts.shape[:2] == (20, 4)
    ok = pts[:, :, 3] >= 0
    np.testing.assert_array_equal(ok, take.valid)
    np.testing.assert_allclose(pts[:, :, :3][ok], take.positions[take.valid], atol=1e-3)


def test_units_converted(tmp_path):
    (tmp_path / "t.csv").write_text("# rate=100 units=m\nframe,time,a.x,a.y,a.z\n0,0,1,2,3\n1,0.01,,,\n")
    take = read_take(tmp_path / "t.csv")
    np.testing.assert_allclose(take.positions[0, 0], [1000, 2000, 3000])
    assert take.valid.tolist() == [[True], [False]]


@pytest.mark.parametrize("name", ["Vicon.c3d", "Qualisys.c3d", "BTS.c3d", "FP_Type1.c3d", "read_NOTworking2.c3d"])
def test_vendor_files_load(vendors, name):
    take = read_take(vendors / name)
    assert take.n_markers > 0 and take.n_frames > 0 and take.rate > 0
    assert np.isfinite(take.positions).all()
    assert take.valid.any()


def test_vendor_units_in_metres_become_mm(vendors):
    take = read_take(vendors / "FP_Type1.c3d")  # POINT:UNITS = m
    assert np.abs(take.positions[take.valid]).max() > 10  # would be < 10 if left in metres


@pytest.mark.parametrize("name,problem", [
    ("Kistler.c3d", "no 3D marker points"),
    ("C3DRotationExample.c3d", "no 3D marker points"),
    ("Optotrak.c3d", "truncated"),
])
def test_broken_vendor_files_clear_error(vendors, name, problem):
    with pytest.raises(TakeFileError, match=problem) as exc:
        read_take(vendors / name)
    assert name in str(exc.value)


def test_bad_files(tmp_path):
    (tmp_path / "x.c3d").write_bytes(b"\x00" * 100)
    with pytest.raises(TakeFileError, match="x.c3d"):
        read_take(tmp_path / "x.c3d")
    (tmp_path / "x.trc").write_text("hello\n")
    with pytest.raises(TakeFileError, match="not a TRC"):
        read_take(tmp_path / "x.trc")
    (tmp_path / "x.csv").write_text("frame,time\n")
    with pytest.raises(TakeFileError, match="rate="):
        read_take(tmp_path / "x.csv")
    with pytest.raises(TakeFileError, match="unknown take format"):
        (tmp_path / "x.bvh").write_text("")
        read_take(tmp_path / "x.bvh")
    with pytest.raises(TakeFileError, match="no such take"):
        read_take(tmp_path / "missing.c3d")


@pytest.mark.parametrize("processor", [84, 85, 86])
def test_c3d_check_reads_a_float_frame_count_in_the_files_own_format(processor):
    """POINT:LONG_FRAMES is a float in many files; in a DEC (VAX) file it is a VAX float, which read as IEEE is
    another number (the check would then call a valid long take truncated)."""
    raw = struct.pack(">f" if processor == 86 else "<f", 70000.0 * (4 if processor == 85 else 1))
    if processor == 85:
        raw = raw[2:4] + raw[0:2]
    assert _int({("POINT", "LONG_FRAMES"): Param(4, (), raw)}, "POINT", "LONG_FRAMES", processor) == 70000


def test_trc_with_more_rows_than_its_numframes_is_refused_at_the_first_extra_row(tmp_path):
    """A header that under-declares its rows is a lie like an over-declaring one; the reader stops at the first row
    past it (naming the line) instead of reading the whole file first."""
    take = Take(["a", "b"], np.zeros((50, 2, 3)), np.ones((50, 2), bool), 60.0)
    write_take(take, tmp_path / "t.trc")
    lines = (tmp_path / "t.trc").read_text().split("\n")
    lines[2] = lines[2].replace("\t50\t2\t", "\t10\t2\t", 1)
    (tmp_path / "t.trc").write_text("\n".join(lines))
    with pytest.raises(TakeFileError, match=r"t.trc:17: more data rows than the header's NumFrames 10"):
        read_take(tmp_path / "t.trc")
