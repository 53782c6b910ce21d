"""The performance suite: figures, not pass/fail tests (``python -m benchmarks``)."""

import livecap  # noqa: F401  (sets single-threaded BLAS before numpy loads)
