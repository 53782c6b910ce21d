"""livecap: labelled facial markers in, blendshape weights out.

Rooms (each package's docstring says what it holds and what it may import):

* ``livecap.core``: the types every package may import (Rig, MarkerLayout, Take, MarkerFrame,
  SolveResult, units, OBJ files), importing nothing of livecap above them.
* ``livecap.calibration``: from a neutral take to a Profile: neutral, head stabilisation, proportion
  warp, gap filling, actor basis, key pairs, a take's solve targets.
* ``livecap.modes``: solver modes by name: the registry and one module per mode family.
* ``livecap.live``: the live pipeline and session files.
* ``livecap.offline``: whole-take solving, accuracy metrics, rig-to-rig weight mapping, the calibration report.
* ``livecap.api``: the Python API (docs/api.md), exported here: ``livecap.solve(...)``, ``livecap.Solver``...
* ``livecap.cli``, ``livecap.demo``, ``livecap.transfer``: the command, the demo generator, rig transfer.

``solvers/`` (numerics), ``transport/`` (sources and sinks) and ``viewer/`` (drawing) sit beside it.
"""

import os

# Per-frame solves work on small matrices, where a multi-threaded BLAS only adds
# synchronisation (measured 2-10x slower p99 on a 2-core machine); set before numpy loads.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import solvers  # noqa: E402, F401 -- before any kernel loads: a writable place for numba's cache (solvers/__init__.py)

_API = ("ApiError", "MarkerFrame", "MarkerLayout", "Profile", "Rig", "Session", "Sink", "SolveResult", "Solver", "Take",
        "Weights", "calibrate", "load_layout", "load_profile", "load_rig", "load_take", "settings_names", "solve")
__all__ = list(_API)


def __getattr__(name: str):
    """The API's names load on first use, so ``import livecap`` (and ``livecap --help``) stays cheap."""
    if name in _API:
        from livecap import api

        return getattr(api, name)
    raise AttributeError(f"module 'livecap' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_API])
