"""benchmarks.batch's child processes import what the benchmark imports, whatever the install layout."""

from __future__ import annotations

import os
import subprocess
import sys

from benchmarks.batch import child_env


def test_the_benchmark_children_import_what_the_parent_imports(tmp_path, monkeypatch):
    extra = tmp_path / "extra"
    extra.mkdir()
    (extra / "only_on_pythonpath.py").write_text("X = 1\n")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(extra), os.environ.get("PYTHONPATH", "")]))
    code = "import only_on_pythonpath, livecap, benchmarks.batch, transport, solvers"
    subprocess.run([sys.executable, "-c", code], env=child_env(), cwd=tmp_path, check=True, timeout=60)
