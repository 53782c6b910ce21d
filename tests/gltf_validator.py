"""Run the Khronos glTF validator (npm ``gltf-validator``, installed by ./dev under tools/gltf) on a file."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

TOOL = Path(__file__).resolve().parents[1] / "tools" / "gltf"


def validate(path: Path) -> dict:
    """The validator's report (its JSON) on ``path``; skips when Node.js or the package is absent."""
    node = shutil.which("node")
    if node is None or not (TOOL / "node_modules" / "gltf-validator").is_dir():
        pytest.skip(f"Khronos gltf-validator not installed (run ./dev: needs node and npm install in {TOOL})")
    out = subprocess.run([node, str(TOOL / "validate.js"), str(path)], capture_output=True, text=True,
                         timeout=120, check=True)
    return json.loads(out.stdout)


def animation_warnings(report: dict) -> list[dict]:
    return [m for m in report["issues"]["messages"] if m["severity"] <= 1 and "ANIMATION" in m["code"]]


def three_load(path: Path) -> dict:
    """What three.js's GLTFLoader (npm ``three``) builds from ``path``: vertex count, morph target
    names, animation tracks; skips when Node.js or the package is absent."""
    node = shutil.which("node")
    if node is None or not (TOOL / "node_modules" / "three").is_dir():
        pytest.skip(f"three.js not installed (run ./dev: needs node and npm install in {TOOL})")
    out = subprocess.run([node, str(TOOL / "three_load.mjs"), str(path)], capture_output=True, text=True,
                         timeout=120, check=True)
    return json.loads(out.stdout)
