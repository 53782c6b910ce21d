"""Whole takes: ``solve`` (stabilise and solve a recorded take), ``metrics`` (accuracy against ground
truth), ``mapping`` (weights from one rig's parameterisation to another's, Lewis et al. 2014 §5.3).

May import ``livecap.core``, ``livecap.calibration``, ``livecap.modes``, ``solvers`` and ``transport``.
"""
