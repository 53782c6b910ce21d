"""Compiled (numba) ``%d`` / ``%.6f`` formatting of number tables, byte for byte what Python's ``%`` writes.

Why: a take's weight curves are ~200 000 numbers per 30 s at 53 shapes; Python's formatting of them was an
eighth of a whole offline solve (docs/performance.md, "Whole takes"). A value is written from the integer
nearest ``|x| * 1e6``; where that product lies within two ulps of a half (where its own rounding could flip
the last digit against the exact decimal value that ``%`` rounds), or the value is not finite or 1e9 or
more, the kernel returns -1 and the caller formats the block with ``%`` instead.
"""

from __future__ import annotations

import math

import numba
import numpy as np

MAX_VALUE = 1e9  # |x| * 1e6 stays below 2^53 with room for the half-way check
BYTES_PER_VALUE = 19  # sign, 9 integer digits, point, 6 decimals, separator
BYTES_PER_INT = 21  # sign and 19 digits of an int64, separator


@numba.njit(cache=True, nogil=True, inline="always")
def _put_int(buf, at, n):
    if n < 0:
        buf[at] = 45  # '-'
        at += 1
        n = -n
    digits = 1
    m = n
    while m >= 10:
        m //= 10
        digits += 1
    for k in range(digits - 1, -1, -1):
        buf[at + k] = 48 + n % 10
        n //= 10
    return at + digits


@numba.njit(cache=True, nogil=True, inline="always")
def _put_fixed6(buf, at, x):
    """``'%.6f' % x`` into ``buf`` at ``at``; returns the end, or -1 where the kernel cannot be sure."""
    if not math.isfinite(x) or abs(x) >= MAX_VALUE:
        return -1
    y = abs(x) * 1e6
    whole = math.floor(y)
    frac = y - whole
    if abs(frac - 0.5) <= 2.0 * (y * 2.220446049250313e-16 + 5e-324):
        return -1
    n = np.int64(whole) + (1 if frac > 0.5 else 0)
    if math.copysign(1.0, x) < 0:
        buf[at] = 45
        at += 1
    at = _put_int(buf, at, n // 1000000)
    buf[at] = 46  # '.'
    n %= 1000000
    for k in range(6, 0, -1):
        buf[at + k] = 48 + n % 10
        n //= 10
    return at + 7


@numba.njit(cache=True, nogil=True)
def format_rows(frames, times, values, buf):
    """Rows ``frame,time,value...`` ending ``\\r\\n`` (as ``csv.writer`` ends them) into ``buf`` (uint8, at least
    ``len(frames) * (BYTES_PER_INT + BYTES_PER_VALUE * (1 + values.shape[1]) + 2)`` long). Returns the bytes
    written, or -1 when a value needs Python's ``%`` (see the module's doc)."""
    at = 0
    for i in range(values.shape[0]):
        at = _put_int(buf, at, frames[i])
        buf[at] = 44
        at = _put_fixed6(buf, at + 1, times[i])
        if at < 0:
            return -1
        for j in range(values.shape[1]):
            buf[at] = 44
            at = _put_fixed6(buf, at + 1, values[i, j])
            if at < 0:
                return -1
        buf[at] = 13
        buf[at + 1] = 10
        at += 2
    return at
