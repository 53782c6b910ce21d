"""Unlabelled marker clouds in, labelled frames out: the labeller (solvers.labelling) fed from a
calibrated profile, as a source wrapper for live sessions and over whole takes offline."""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Iterator

import numpy as np

from livecap.calibration.profile import Profile
from livecap.core.take import MarkerFrame, Take
from solvers.labelling import Fit, LabellerSettings, MarkerLabeller

log = logging.getLogger("livecap.input")


def labeller_for(profile: Profile, settings: LabellerSettings | None = None) -> MarkerLabeller:
    """A labeller on the profile's actor neutral, stable markers and marker basis."""
    return MarkerLabeller(profile.source_neutral, profile.stable, profile.basis, profile.lower, profile.upper,
                          settings)


def rival_warning(rival: tuple[Fit, Fit], frame: int) -> str:
    """One line naming the ambiguity: two faces in the cloud, both fits' scores, which one was taken."""
    def score(fit: Fit) -> str:
        x, y, z = fit.centre
        return f"{fit.labelled} labels within the gate, cost {fit.cost:.0f} mm^2, at ({x:.0f}, {y:.0f}, {z:.0f}) mm"

    taken, other = rival
    return (f"frame {frame}: two faces in the cloud; labelling the one fitted first ({score(taken)}), not the "
            f"other ({score(other)}): if that is the wrong actor, keep only one face in the stream")


class LabelledSource:
    """Wraps a source of unlabelled frames (each frame's valid points are the cloud; their order
    and count mean nothing) and yields frames in the profile's label order.

    Everything else of the wrapped source (``pending``, ``stop``, ``close``, ``bad``) shows
    through; the labelling time is added to ``last_decode_seconds`` (the pipeline's receive stage).
    """

    def __init__(self, source: Iterable[MarkerFrame], profile: Profile,
                 settings: LabellerSettings | None = None) -> None:
        self.source = source
        self.labels = list(profile.labels)
        self.labeller = labeller_for(profile, settings)
        self.last_decode_seconds = 0.0
        self.label_seconds = 0.0

    def __getattr__(self, name: str):
        return getattr(self.source, name)

    def __iter__(self) -> Iterator[MarkerFrame]:
        for frame in self.source:
            t0 = time.perf_counter()
            pts = np.asarray(frame.positions, dtype=np.float64).reshape(-1, 3)
            valid = np.asarray(frame.valid, dtype=bool).reshape(-1)
            cloud = pts[valid]
            near = self.labeller.near(cloud)  # a large cloud costs the tracked face's neighbourhood only
            out = self.labeller.step(cloud if near is None else cloud[near])
            if out.initialised and self.labeller.rival:
                log.warning("%s", rival_warning(self.labeller.rival, frame.frame))
            self.label_seconds = time.perf_counter() - t0
            self.last_decode_seconds = getattr(self.source, "last_decode_seconds", 0.0) + self.label_seconds
            yield MarkerFrame(frame.frame, frame.timestamp, out.positions, out.valid)

    @property
    def initialisations(self) -> int:
        return self.labeller.initialisations


def label_take(cloud: Take, profile: Profile, settings: LabellerSettings | None = None,
               labeller: MarkerLabeller | None = None) -> tuple[Take, np.ndarray]:
    """Label every frame of a take whose point names mean nothing (``*12``-style or wrong).

    Returns the take in the profile's label order and, per frame and label, the cloud column it
    was given (-1: missing). ``labeller``: one of your own (to read its counters afterwards).
    """
    lab = labeller if labeller is not None else labeller_for(profile, settings)
    n = len(profile.labels)
    pos = np.zeros((cloud.n_frames, n, 3))
    valid = np.zeros((cloud.n_frames, n), dtype=bool)
    columns = np.full((cloud.n_frames, n), -1, dtype=np.int64)
    prev_cols = np.zeros(0, dtype=np.int64)
    for f in range(cloud.n_frames):
        cols = np.flatnonzero(cloud.valid[f])
        near = lab.near(cloud.positions[f, cols])
        if near is not None:
            cols = cols[near]
        out = lab.step(cloud.positions[f, cols])
        if out.initialised and lab.rival:
            log.warning("%s", rival_warning(lab.rival, cloud.first_frame + f))
        pos[f], valid[f] = out.positions, out.valid
        columns[f, out.valid] = cols[out.index[out.valid]]
        if f > 0 and out.late is not None and len(out.late):  # offline: a confirmed return starts a frame earlier
            c = prev_cols[out.late_index]
            pos[f - 1, out.late] = cloud.positions[f - 1, c]
            valid[f - 1, out.late] = True
            columns[f - 1, out.late] = c
        prev_cols = cols
    return Take(list(profile.labels), pos, valid, cloud.rate, cloud.first_frame), columns
