"""Bounded line reading for the text take formats (TRC, CSV).

A line longer than any honest row (``CELL`` characters a cell) is refused before it is read
whole, so a 50 MB field costs no more memory than a valid row.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import IO

from transport.errors import TakeFileError

CELL = 64  # characters a cell may take (a float's repr is at most 24; labels are short)
HEADER_LINE = 1 << 20  # a header line of this length names ~30 000 markers


def bounded_line(fh: IO[str], path: object, limit: int, what: str) -> str:
    line = fh.readline(limit + 1)
    if len(line) > limit:
        raise TakeFileError(f"{path}: {what} is longer than {limit} characters, more than any row of this take")
    return line


def bounded_lines(fh: IO[str], path: object, limit: int, first: int) -> Iterator[tuple[int, str]]:
    """(line number, line) for the rest of the file, each at most ``limit`` characters."""
    lineno = first
    while line := bounded_line(fh, path, limit, f"line {lineno}"):
        yield lineno, line
        lineno += 1
