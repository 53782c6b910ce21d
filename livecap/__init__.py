"""livecap: labelled facial markers in, blendshape weights out."""

import os

# Per-frame solves work on small matrices, where a multi-threaded BLAS only adds
# synchronisation (measured 2-10x slower p99 on a 2-core machine); set before numpy loads.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
