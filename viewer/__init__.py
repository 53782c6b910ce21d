"""moderngl preview of a rig driven by solved weights (draws only).

May import ``livecap.core`` and the pure geometry of ``solvers.rigid``; nothing that solves or sends.
"""
