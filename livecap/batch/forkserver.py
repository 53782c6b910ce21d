"""Imported once by the forkserver that ``livecap batch``'s LocalCluster forks its workers from
(runner.FORKSERVER_PRELOAD), so every worker starts with what is loaded here instead of loading it again:
numba's typing and target contexts (0.2 CPU s a process, profiled in docs/batch.md), the kernels of the
jobs the client named in LIVECAP_BATCH_WARM (runner.warm_kernels; compiled into the on-disk cache once if it
is cold), and their rigs, profiles and prepared solvers (worker.PRELOADED, which each worker's cache
adopts). Nothing here may raise: the forkserver would not start."""

from __future__ import annotations

import logging
import os
import pickle
from pathlib import Path


def _load() -> None:
    from numba.core.registry import cpu_target

    from livecap.batch.runner import WARM_ENV, warm_kernels
    from livecap.batch.worker import PRELOADED

    cpu_target.target_context.refresh()
    path = os.environ.get(WARM_ENV)
    if path:
        warm_kernels(pickle.loads(Path(path).read_bytes()), PRELOADED)


try:
    _load()
except Exception as exc:  # the workers load what they need themselves
    logging.getLogger(__name__).warning("batch forkserver: nothing preloaded (%s)", exc)
