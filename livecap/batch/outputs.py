"""A solved take to its output file, in the bytes ``livecap solve`` writes; written under a temporary
folder and moved into place, so an output that exists is always complete (what resuming relies on)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from livecap.batch.jobs import RECORDS, Job
from livecap.core.result import SolveResult
from livecap.offline.solve import SolvedTake
from transport.recorders import JsonlRecorder
from transport.weights_csv import write_weights_csv

FORMATS = ("csv", "jsonl", "glb")


def _write_jsonl(path: Path, solved: SolvedTake, residual: np.ndarray) -> None:
    """One JSON object per frame (transport.recorders' JSONL, what a live session records)."""
    rec = JsonlRecorder(path)
    per_frame = solved.solve_seconds / max(len(solved.weights), 1)
    try:
        for i, w in enumerate(solved.weights):
            rec.publish(SolveResult(solved.first_frame + i, i / solved.rate, solved.names, w,
                                    solved.head_rotation[i], solved.head_translation[i],
                                    float(np.nan_to_num(residual[i])), per_frame))
    finally:
        rec.close()


def write_output(job: Job, solved: SolvedTake, residual: np.ndarray, rig=None) -> None:
    tmp_dir = Path(job.out_dir) / RECORDS / f"tmp-{os.getpid()}"
    tmp_dir.mkdir(parents=True, exist_ok=True)
    tmp = tmp_dir / job.output.name  # same name: the .glb's animation is named after the file
    if job.fmt == "csv":
        write_weights_csv(tmp, solved.names, solved.weights, solved.rate, solved.first_frame)
    elif job.fmt == "jsonl":
        _write_jsonl(tmp, solved, residual)
    elif job.fmt == "glb":
        from livecap.offline.glb import write_solved_glb

        write_solved_glb(str(tmp), rig, solved, max(1, int(job.spec.neutral_seconds * solved.rate)))
    else:
        raise ValueError(f"--format {job.fmt}: choose from {', '.join(FORMATS)}")
    os.replace(tmp, job.output)
    try:
        tmp_dir.rmdir()
    except OSError:
        pass  # another take of this worker process is being written there
