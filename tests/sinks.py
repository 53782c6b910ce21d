"""Test helpers: a sink that keeps what it is given."""


class Capture:
    """Keeps every published result (a sink for tests of the pipeline's logic)."""

    def __init__(self):
        self.results = []

    def publish(self, r):
        self.results.append(r)

    def close(self):
        pass
