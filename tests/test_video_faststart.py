"""The preview MP4 is streamable: its index (moov) comes before the media data (mdat)."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from viewer.offscreen import FrameWriter


def top_level_atoms(path: Path) -> list[str]:
    """The ISO BMFF top-level box types in file order (ISO/IEC 14496-12 §4.2: size, type, 64-bit size if 1)."""
    data, pos, atoms = path.read_bytes(), 0, []
    while pos + 8 <= len(data):
        size, kind = struct.unpack(">I4s", data[pos:pos + 8])
        if size == 1:
            size = struct.unpack(">Q", data[pos + 8:pos + 16])[0]
        elif size == 0:
            size = len(data) - pos
        assert size >= 8, f"bad box size {size} at {pos}"
        atoms.append(kind.decode("latin-1"))
        pos += size
    assert pos == len(data)
    return atoms


def test_preview_mp4_has_its_index_first(tmp_path):
    out = tmp_path / "p.mp4"
    rng = np.random.default_rng(0)
    with FrameWriter(out, None, 30.0, (64, 48)) as writer:
        for _ in range(10):
            writer.write(rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
    atoms = top_level_atoms(out)
    assert "moov" in atoms and "mdat" in atoms
    assert atoms.index("moov") < atoms.index("mdat"), atoms
