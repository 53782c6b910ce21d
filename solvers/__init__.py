"""Numerical solvers: pure numpy/scipy, no sockets, files or GL.

Each solver is prepared once (factorisations, bases) and then driven per frame by
``step(target, valid) -> weights`` with ``target`` the stabilised marker displacements (n x 3)
and ``valid`` the visible markers (n bool).
"""
