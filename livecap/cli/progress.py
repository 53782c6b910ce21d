"""Progress feedback for commands that can take more than a couple of seconds.

rich on stderr, so stdout (tables, paths) stays clean for pipes: a live bar or spinner only when
stderr is a terminal, and in every case one summary line when the work ends ("solving (robust):
3600/3600 in 4.2 s"), so a log of a batch job still says where the time went.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from rich.console import Console


def _console() -> Console:
    return Console(stderr=True, highlight=False)


def _summary(console: Console, description: str, seconds: float, count: str = "") -> None:
    console.print(f"{description}: {count + ' ' if count else ''}in {seconds:.1f} s", markup=False, soft_wrap=True)


@contextmanager
def progress_bar(description: str, total: int) -> Iterator[Callable[[int, int], None]]:
    """A bar over ``total`` steps; yields ``update(done, total)``."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    console = _console()
    done_box = [0]
    start = time.perf_counter()
    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                  TimeRemainingColumn(), transient=True, console=console, disable=not console.is_terminal) as prog:
        task = prog.add_task(description, total=total)

        def update(done: int, total_: int) -> None:
            done_box[0] = done
            if done % 16 == 0 or done == total_:
                prog.update(task, completed=done, total=total_)

        yield update
    _summary(console, description, time.perf_counter() - start, f"{done_box[0]}/{total}")


@contextmanager
def stage(description: str) -> Iterator[None]:
    """A spinner for one step without a count (calibration, tuning, loading a rig)."""
    console = _console()
    start = time.perf_counter()
    if console.is_terminal:
        with console.status(description):
            yield
    else:
        yield
    _summary(console, description, time.perf_counter() - start)
