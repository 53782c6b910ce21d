"""The live path: ``pipeline`` (source -> stabilise -> solver -> sinks, one frame at a time) and
``session`` (a ``livecap run`` set-up kept in TOML).

May import ``livecap.core``, ``livecap.calibration``, ``livecap.modes``, ``solvers`` and ``transport``.
"""
