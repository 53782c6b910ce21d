"""Numerical solvers: pure numpy/scipy, no sockets, files or GL.

Each solver is prepared once (factorisations, bases) and then driven per frame by
``step(target, valid) -> weights`` with ``target`` the stabilised marker displacements (n x 3)
and ``valid`` the visible markers (n bool).
"""

import os
import sys


def _writable(path: str) -> bool:
    """numba's own test of a cache folder (make it, write a file in it), without importing tempfile (5 ms)."""
    probe = os.path.join(path, f".livecap-probe-{os.getpid()}")
    try:
        os.makedirs(path, exist_ok=True)
        os.close(os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
        os.unlink(probe)
    except OSError:
        return False
    return True


def numba_cache_dir(env: dict | None = None, here: str = os.path.dirname(os.path.abspath(__file__)),
                    writable=_writable) -> str | None:
    """Where numba must keep the compiled kernels, or None where it finds a place itself.

    numba caches a ``cache=True`` kernel beside its source (``__pycache__``), else in the user's cache folder, else
    refuses to import the module at all ("cannot cache function ...: no locator available"): an install whose
    package folder is read-only, run by a user without a writable home (a service, a container), would not start.
    There: a per-user folder in the temp dir, so the ~10-25 s of compiling is paid once, not per process or never
    (issue 39; docs/performance.md, "`kalman` against `robust`"). ``NUMBA_CACHE_DIR`` set wins."""
    env = os.environ if env is None else env
    if env.get("NUMBA_CACHE_DIR") or writable(os.path.join(here, "__pycache__")):
        return None
    home = env.get("HOME") or os.path.expanduser("~")
    if writable(os.path.join(env.get("XDG_CACHE_HOME") or os.path.join(home, ".cache"), "numba")):
        return None
    import tempfile

    return os.path.join(tempfile.gettempdir(), f"livecap-numba-{os.getuid()}")


_cache = numba_cache_dir()
if _cache is not None:
    os.environ["NUMBA_CACHE_DIR"] = _cache
    if "numba" in sys.modules:  # numba read its settings already: set the one the cache locators read
        sys.modules["numba"].config.CACHE_DIR = _cache
