"""Core types every package may import: Rig, MarkerLayout, Take, MarkerFrame, SolveResult, units, OBJ.

May import numpy/scipy and ``solvers`` only; nothing else of livecap, transport or viewer.
"""
