"""livecap: labelled facial markers in, blendshape weights out.

Rooms (each package's docstring says what it holds and what it may import):

* ``livecap.core``: the types every package may import (Rig, MarkerLayout, Take, MarkerFrame,
  SolveResult, units, OBJ files), importing nothing of livecap above them.
* ``livecap.calibration``: from a neutral take to a Profile: neutral, head stabilisation, proportion
  warp, gap filling, actor basis, key pairs, the calibration report.
* ``livecap.modes``: solver modes by name: the registry and one module per mode family.
* ``livecap.live``: the live pipeline and session files.
* ``livecap.offline``: whole-take solving, accuracy metrics, rig-to-rig weight mapping.
* ``livecap.cli``, ``livecap.demo``, ``livecap.transfer``: the command, the demo generator, rig transfer.

``solvers/`` (numerics), ``transport/`` (sources and sinks) and ``viewer/`` (drawing) sit beside it.
"""

import os

# Per-frame solves work on small matrices, where a multi-threaded BLAS only adds
# synchronisation (measured 2-10x slower p99 on a 2-core machine); set before numpy loads.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
