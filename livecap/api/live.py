"""A live session from Python: any iterable of frames in, any objects with ``publish``/``close`` out
(the pipeline ``livecap run`` drives, with its per-frame error containment)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Protocol

from livecap.api.errors import ApiError
from livecap.api.solve import Solver
from livecap.core.result import SolveResult
from livecap.core.take import MarkerFrame, Take


class Sink(Protocol):
    """What a session publishes to: ``publish`` each result, ``close`` once at the end."""

    def publish(self, result: SolveResult) -> None: ...

    def close(self) -> None: ...


class Session:
    """``Session(source, solver, sinks).run()``: solve every frame of ``source`` with ``solver``'s profile,
    mode and settings and publish each result to every sink.

    ``source`` is an iterable of :class:`MarkerFrame` in ``solver.profile.labels`` order (a transport
    source, a generator...) or a :class:`Take` (its frames, selected to the profile's labels). A sink
    that raises is counted and logged, never ends the session (``stats()["errors"]``).
    """

    def __init__(self, source: Iterable[MarkerFrame] | Take, solver: Solver, sinks: Iterable[Sink] = (), *,
                 max_frames: int | None = None) -> None:
        from livecap.live.pipeline import Pipeline

        if not isinstance(solver, Solver):
            raise ApiError("solver", f"expected a livecap.Solver, got {type(solver).__name__}")
        sinks = list(sinks)
        for i, sink in enumerate(sinks):
            if not (callable(getattr(sink, "publish", None)) and callable(getattr(sink, "close", None))):
                raise ApiError(f"sinks[{i}]", f"{type(sink).__name__} has no publish(result) and close()")
        if isinstance(source, Take):
            source = source.select(solver.profile.labels).frames()
        self._pipeline = Pipeline(source, sinks, profile=solver.profile, mode=solver.mode, options=solver.settings,
                                  max_frames=max_frames)

    def run(self) -> dict:
        """Run until the source ends (or ``max_frames``, or :meth:`stop`), close the sinks, return the stats."""
        return self._pipeline.run()

    def stop(self) -> None:
        """End :meth:`run` after the frame in hand (thread-safe)."""
        self._pipeline.stop()

    def stats(self) -> dict:
        """Frames in and out, per-stage timing percentiles, counted errors."""
        return self._pipeline.stats()
