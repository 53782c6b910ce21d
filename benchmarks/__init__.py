"""The performance suite: figures, not pass/fail tests (``python -m benchmarks``)."""
