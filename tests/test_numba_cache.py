"""Compiled kernels are compiled once per machine, not once per process (issue 39.4): a fresh process that finds
them uncompiled pays ~10-25 s (docs/performance.md, "`kalman` against `robust`")."""

from __future__ import annotations

import ast
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("livecap", "solvers", "transport", "viewer")


def _numba_calls(tree: ast.AST):
    """Every ``numba.njit(...)``/``numba.jit(...)`` call and bare ``@numba.njit`` decorator in a module."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, (ast.Attribute, ast.Name)):
            name = node.func.attr if isinstance(node.func, ast.Attribute) else node.func.id
            if name in ("njit", "jit"):
                yield node, {k.arg: k.value for k in node.keywords}
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for d in node.decorator_list:
                if isinstance(d, (ast.Attribute, ast.Name)) and getattr(d, "attr", getattr(d, "id", "")) in ("njit",
                                                                                                            "jit"):
                    yield d, {}


def test_every_kernel_is_cached_on_disk():
    missing = []
    count = 0
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            for node, kw in _numba_calls(ast.parse(path.read_text())):
                count += 1
                cache = kw.get("cache")
                if not (isinstance(cache, ast.Constant) and cache.value is True):
                    missing.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert count >= 10, "the scan found no kernels: has numba's spelling changed?"
    assert not missing, f"numba kernels without cache=True (compiled again in every process): {missing}"


def test_a_fresh_process_loads_the_kernels_another_compiled(tmp_path):
    """Through ``NUMBA_CACHE_DIR`` (where an install's own folder is not writable): the second process hits the
    cache for the kalman filter's kernels and compiles nothing."""
    code = ("import numpy as np\n"
            "from solvers import marker_kalman_kernels as k\n"
            "from solvers.marker_kalman import StreamingMarkerKalman\n"
            "f = StreamingMarkerKalman(3)\n"
            "[f.step(np.zeros((3, 3)), np.ones(3, bool)) for _ in range(3)]\n"
            "print(sum(k.frame.stats.cache_hits.values()), sum(k.frame.stats.cache_misses.values()))\n")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path),
           "PYTHONPATH": os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}
    runs = [subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True,
                           timeout=300).stdout.split() for _ in range(2)]
    assert runs[0] == ["0", "1"], runs  # compiled into the empty cache (a frame is one call: step, choose, output)
    assert runs[1] == ["1", "0"], runs  # loaded from it
    assert any(tmp_path.rglob("marker_kalman_kernels.frame-*.nbi"))


def test_a_cache_place_is_chosen_only_where_numba_has_none():
    from solvers import numba_cache_dir

    def only(*ok):
        return lambda path: any(path.startswith(p) for p in ok)

    assert numba_cache_dir({"NUMBA_CACHE_DIR": "/x"}, "/pkg", only()) is None
    assert numba_cache_dir({}, "/pkg", only("/pkg")) is None
    assert numba_cache_dir({"XDG_CACHE_HOME": "/c"}, "/pkg", only("/c/numba")) is None
    assert numba_cache_dir({"HOME": "/h"}, "/pkg", only("/h/.cache/numba")) is None
    assert numba_cache_dir({"HOME": "/h"}, "/pkg", only()).startswith(tempfile.gettempdir())


def test_kernels_import_and_cache_where_neither_the_package_nor_home_is_writable(tmp_path):
    """numba alone raises 'no locator available' on importing a cache=True kernel there; solvers points it at the
    temp dir. Simulated as root can: the package's __pycache__ and the cache home are files, not folders."""
    pkg = tmp_path / "site" / "solvers"
    pkg.mkdir(parents=True)
    for name in ("__init__.py", "qp_kernels.py"):
        shutil.copy(ROOT / "solvers" / name, pkg / name)
    (pkg / "__pycache__").write_text("not a folder")
    blocked = tmp_path / "blocked"
    blocked.write_text("not a folder")
    temp = tmp_path / "temp"
    temp.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "PYTHONPATH")}
    env.update(HOME=str(blocked), XDG_CACHE_HOME=str(blocked / "cache"), TMPDIR=str(temp),
               PYTHONPATH=str(pkg.parent), PYTHONDONTWRITEBYTECODE="1")
    code = ("import numpy as np\nfrom solvers.qp_kernels import smallest_eigenvalue as f\n"
            "print(round(f(np.eye(2)), 6))\n")
    r = subprocess.run([sys.executable, "-c", code], env=env, cwd=tmp_path, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0 and r.stdout.split() == ["1.0"], r.stderr[-800:]
    assert any(temp.rglob("qp_kernels.smallest_eigenvalue-*.nbi"))
