"""Solver modes by name: ``registry`` (MODES, build a solver from a Profile) and one module per family:
``movement`` (Seol movement matching), ``robust_movement`` (its noise-robust offline solve), ``robust``
(the sparse fit with data-selected regularisation and tracking), ``per_frame`` (qp, rbf).

May import ``livecap.core``, ``livecap.calibration`` and ``solvers``.
"""
