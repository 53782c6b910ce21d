"""Calibration: a neutral take and a target rig to a Profile (everything a solver needs).

``profile`` (neutral, proportion warp, the Profile file), ``stabilise`` (head-motion removal),
``warp`` (Seol §3.2 RBF warp), ``gaps`` (gap filling), ``actor_basis`` and ``keys`` (Curio / Pyun
examples), ``report`` (what each step buys). May import ``livecap.core`` and ``solvers``.
"""
