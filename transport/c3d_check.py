"""Check a C3D file's header and parameter section before ezc3d reads it.

ezc3d trusts the file: a count flipped by one bad byte makes it allocate gigabytes
(``std::bad_alloc`` after 10 s) or read past its buffers (a segmentation fault), both
outside Python's reach. This walks the parameter section by the C3D specification
(c3d.org, "The C3D File Format User Guide", chapters 2-3: header words, parameter records)
and checks every count against the bytes the file really holds, so that what ezc3d is
handed needs no more memory than a valid file of its size. Errors name the file and the field.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from transport.errors import TakeFileError

BLOCK = 512
INTEL, DEC, MIPS = 84, 85, 86
TYPE_SIZE = {-1: 1, 1: 1, 2: 2, 4: 4}  # parameter data types: char, byte, int16, float
MAX_WALK = 1 << 20  # elements a parameter's dimensions may span, even when one of them is 0


@dataclass
class Param:
    type: int
    dims: tuple[int, ...]
    data: bytes


@dataclass
class C3DLayout:
    """What the header and parameters claim, once checked against the file."""

    processor: int
    points: int
    analogs: int  # analog samples per 3D frame, all channels
    frames: int
    is_float: bool
    data_start: int  # byte offset
    params: dict[tuple[str, str], Param] = field(default_factory=dict)


def _float(raw: bytes, processor: int) -> float:
    if processor == DEC:  # VAX F-float: 16-bit halves swapped, exponent bias 2 higher than IEEE
        return float(np.frombuffer(raw[2:4] + raw[0:2], "<f4")[0]) / 4.0
    return struct.unpack(">f" if processor == MIPS else "<f", raw)[0]


def check_c3d(path: Path) -> C3DLayout:
    """Validate ``path``'s structure and counts; raise :class:`TakeFileError` naming the field."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(BLOCK)
        if len(head) < BLOCK:
            raise TakeFileError(f"{path}: shorter than a C3D header ({size} bytes)")
        if head[1] != 0x50:
            raise TakeFileError(f"{path}: not a C3D file (header key is {head[1]:#x}, expected 0x50)")
        pstart = (head[0] - 1) * BLOCK
        if head[0] < 2 or pstart + 4 > size:
            raise TakeFileError(f"{path}: header's parameter block {head[0]} is outside the file ({size} bytes)")
        fh.seek(pstart)
        phead = fh.read(4)
        processor = phead[3] if len(phead) == 4 else 0
        if processor not in (INTEL, DEC, MIPS):
            raise TakeFileError(f"{path}: parameter section's processor type is {processor} (expected 84, 85 or 86)")
        end = "<" if processor != MIPS else ">"
        n_points, n_analog, first, last = struct.unpack(end + "HHHH", head[2:10])
        scale = _float(head[12:16], processor)
        data_block = struct.unpack(end + "H", head[16:18])[0]
        if not data_block > head[0]:
            raise TakeFileError(f"{path}: header's data start block {data_block} is not after the parameters "
                                f"(block {head[0]})")
        data_start = (data_block - 1) * BLOCK
        if data_start > size:
            raise TakeFileError(f"{path}: header's data start block {data_block} is past the end of the file "
                                f"({size} bytes)")
        # the section's own block count and the header's data start disagree in real files (Kistler): the
        # records may run to whichever is further
        fh.seek(pstart + 4)
        section = fh.read(max(data_start, pstart + phead[2] * BLOCK) - pstart - 4)
    params = _parameters(path, section, pstart + 4, end)
    is_float = not (math.isfinite(scale) and scale >= 0)
    for name in ("USED", "SCALE", "RATE") if n_points else ():
        if ("POINT", name) not in params:
            raise TakeFileError(f"{path}: the header says {n_points} points but there is no POINT:{name} parameter")
        if params[("POINT", name)].type not in (1, 2, 4) or _count(params[("POINT", name)]) < 1:
            raise TakeFileError(f"{path}: POINT:{name} holds no number")
    used = _int(params, "POINT", "USED", processor)
    if used is not None and used != n_points:
        raise TakeFileError(f"{path}: POINT:USED is {used} but the header says {n_points} points")
    a_used = _int(params, "ANALOG", "USED", processor) or 0
    if a_used < 0:
        raise TakeFileError(f"{path}: ANALOG:USED is {a_used}")
    if a_used and n_analog % a_used:
        raise TakeFileError(f"{path}: header's {n_analog} analog samples per frame are not a multiple of "
                            f"ANALOG:USED {a_used}")
    for name in ("SCALE", "OFFSET"):
        p = params.get(("ANALOG", name))
        if a_used and (p is None or _count(p) < a_used):  # ezc3d indexes them per channel, unchecked
            raise TakeFileError(f"{path}: ANALOG:{name} has {p and _count(p)} values for {a_used} channels")
    frames = last - first + 1 if last >= first else 0
    for group, name in (("POINT", "FRAMES"), ("POINT", "LONG_FRAMES")):
        n = _int(params, group, name, processor, unsigned=True)
        if n is not None and n > frames and (last == 0xFFFF or n > 0xFFFF):
            frames = n  # more frames than a header word holds
    width = 4 if is_float else 2
    need = frames * (4 * n_points + n_analog) * width
    if data_start + need > size:
        raise TakeFileError(
            f"{path}: truncated C3D: header declares {frames} frames of {n_points} points and {n_analog} analog "
            f"samples ({need} bytes of data), the file holds {size - data_start} after its data start")
    rot = _int(params, "ROTATION", "USED", processor) or 0
    if rot:
        block = _int(params, "ROTATION", "DATA_START", processor, unsigned=True) or 0
        ratio = _int(params, "ROTATION", "RATIO", processor) or 1
        rneed = frames * max(ratio, 1) * rot * 17 * 4
        if block < 1 or (block - 1) * BLOCK + rneed > size:
            raise TakeFileError(f"{path}: ROTATION:USED {rot} at ROTATION:DATA_START {block} needs {rneed} bytes "
                                f"the file does not hold ({size} bytes)")
    return C3DLayout(processor, n_points, n_analog, frames, is_float, data_start, params)


def _parameters(path: Path, sec: bytes, offset: int, end: str) -> dict[tuple[str, str], Param]:
    """Walk the parameter records (C3D User Guide ch. 3); every length must stay inside ``sec``."""
    groups: dict[int, str] = {}
    pending: list[tuple[int, str, Param]] = []
    pos = 0
    while True:
        if pos + 2 > len(sec):
            raise TakeFileError(f"{path}: parameter section runs past its end at byte {offset + pos}")
        nchar, gid = struct.unpack("bb", sec[pos:pos + 2])
        if nchar == 0 or gid == 0:
            break
        at = offset + pos
        p = pos + 2
        name = sec[p:p + abs(nchar)].decode("latin-1").strip().upper()
        shown = name if len(name) <= 32 else name[:32] + "..."  # a damaged record may "name" 127 bytes
        p += abs(nchar)
        if p + 2 > len(sec):
            raise TakeFileError(f"{path}: parameter record {shown!r} at byte {at} runs past the section")
        nxt = struct.unpack(end + "H", sec[p:p + 2])[0]
        p += 2
        if gid < 0:
            groups[-gid] = name
        else:
            if p + 2 > len(sec):
                raise TakeFileError(f"{path}: parameter {shown!r} at byte {at} runs past the section")
            ptype, ndim = struct.unpack("bb", sec[p:p + 2])
            p += 2
            if ptype not in TYPE_SIZE:
                raise TakeFileError(f"{path}: parameter {shown!r} at byte {at} has data type {ptype} "
                                    f"(expected -1, 1, 2 or 4)")
            if not 0 <= ndim <= 7:
                raise TakeFileError(f"{path}: parameter {shown!r} at byte {at} has {ndim} dimensions (at most 7)")
            dims = tuple(sec[p:p + ndim])
            p += ndim
            n = TYPE_SIZE[ptype] * math.prod(dims)
            # ezc3d walks every dimension before an empty one: (255, 255, 255, 255, 0) holds nothing but
            # costs 4e9 steps
            walk = math.prod(d for d in dims if d)
            if walk > MAX_WALK:
                raise TakeFileError(f"{path}: parameter {shown!r} at byte {at} declares dimensions {list(dims)}")
            if len(dims) != ndim or p + n + 1 > len(sec):
                raise TakeFileError(f"{path}: parameter {shown!r} at byte {at} declares dimensions {list(dims)} "
                                    f"({n} bytes), more than the parameter section holds")
            pending.append((gid, name, Param(ptype, dims, sec[p:p + n])))
            p += n
        if p + 1 > len(sec):
            raise TakeFileError(f"{path}: parameter record {shown!r} at byte {at} runs past the section")
        desc = struct.unpack("b", sec[p:p + 1])[0]
        if desc < 0:  # a signed byte (ezc3d reads a negative length as a huge one)
            raise TakeFileError(f"{path}: parameter record {shown!r} at byte {at} has description length {desc}")
        p += 1 + desc
        if p > len(sec):
            raise TakeFileError(f"{path}: parameter record {shown!r} at byte {at} runs past the section")
        if nxt == 0:
            break
        new = pos + 2 + abs(nchar) + nxt
        if new > len(sec):
            raise TakeFileError(f"{path}: parameter record {shown!r} at byte {at} points to byte {offset + new}, "
                                f"outside the parameter section")
        if new < p:  # ezc3d loops for ever on a record that overruns its successor
            raise TakeFileError(f"{path}: parameter record {shown!r} at byte {at} is {p - pos} bytes long but points "
                                f"to the next record {new - pos} bytes on")
        pos = new
    out: dict[tuple[str, str], Param] = {}
    for gid, name, prm in pending:
        if gid not in groups:
            raise TakeFileError(f"{path}: parameter {name[:32]!r} belongs to group {gid}, which the file never defines")
        out[(groups[gid], name)] = prm
    return out


def _count(p: Param) -> int:
    return math.prod(p.dims) if p.dims else 1


def _int(params: dict, group: str, name: str, processor: int, unsigned: bool = False) -> int | None:
    """A parameter's first value as an integer, read in the file's processor format (a DEC file's floats are VAX)."""
    end = ">" if processor == MIPS else "<"
    p = params.get((group, name))
    if p is None or not p.data:
        return None
    if p.type == 2 and len(p.data) >= 2:
        return struct.unpack(end + ("H" if unsigned else "h"), p.data[:2])[0]
    if p.type == 1:
        return p.data[0]
    if p.type == 4 and len(p.data) >= 4:
        v = _float(p.data[:4], processor)
        return int(v) if math.isfinite(v) and 0 <= v < 2**31 else None
    return None
