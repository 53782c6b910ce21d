"""The labelling study: a labelled take with ground truth, scrambled into clouds (labels
stripped, points shuffled, ghosts, occlusion bursts), labelled back, and solved; scored by right
labels, swap length and the solve's weight RMSE against the labelled solve of the same occluded take."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from livecap.calibration.profile import Profile
from livecap.core.take import Take
from livecap.demo.unlabelled import LabelScores, score, scramble
from livecap.live.unlabelled import label_take, labeller_for
from livecap.modes.registry import build_solver
from livecap.offline.solve import solve_take
from solvers.labelling import LabellerSettings


@dataclass
class LabellingStudy:
    scores: LabelScores
    rmse_labelled: float  # solve of the occluded take with its true labels
    rmse_unlabelled: float  # solve of the same take labelled back from clouds
    label_us_per_frame: float
    solve_us_per_frame: float
    initialisations: int

    @property
    def rmse_ratio(self) -> float:
        return self.rmse_unlabelled / self.rmse_labelled


def _rmse(take: Take, profile: Profile, truth: np.ndarray, mode: str) -> tuple[float, float]:
    solver = build_solver(mode, profile, {})
    solved = solve_take(take, profile, solver)
    return float(np.sqrt(np.mean((solved.weights - truth) ** 2))), solved.solve_seconds / take.n_frames


def labelling_study(take: Take, profile: Profile, truth: np.ndarray, *, seed: int = 0, ghosts: int = 2,
                    occlusion: float = 0.05, mode: str = "robust",
                    settings: LabellerSettings | None = None) -> LabellingStudy:
    sc = scramble(take.select(profile.labels), seed=seed, ghosts=ghosts, occlusion=occlusion)
    t0 = time.perf_counter()
    labeller = labeller_for(profile, settings)
    labelled, columns = label_take(sc.cloud, profile, labeller=labeller)
    label_s = (time.perf_counter() - t0) / take.n_frames
    rmse_l, solve_s = _rmse(sc.occluded, profile, truth, mode)
    rmse_u, _ = _rmse(labelled, profile, truth, mode)
    return LabellingStudy(score(columns, sc.source), rmse_l, rmse_u, label_s * 1e6, solve_s * 1e6,
                          labeller.initialisations)
