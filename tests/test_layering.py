"""The layering of DESIGN.md, as import-linter contracts (``[tool.importlinter]`` in
pyproject.toml), checked on every test run.

The repository keeps its layers as top-level folders that install as ``adaptnav.<folder>``
(pyproject ``package-dir``); import-linter reads a package from one directory tree, so
the check runs on a copy of the sources laid out as installed."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ("fusion", "calibration", "sonar", "sim", "service")


def _lint_imports() -> Path | None:
    exe = Path(sys.executable).with_name("lint-imports")
    return exe if exe.exists() else None


@pytest.mark.skipif(_lint_imports() is None, reason="import-linter not installed (pip install -e '.[test]')")
def test_import_contracts_hold(tmp_path):
    pkg = tmp_path / "adaptnav"
    shutil.copytree(ROOT / "adaptnav", pkg, ignore=shutil.ignore_patterns("__pycache__"))
    for layer in LAYERS:
        shutil.copytree(ROOT / layer, pkg / layer, ignore=shutil.ignore_patterns("__pycache__", "*.toml"))
    env = dict(os.environ, PYTHONPATH=str(tmp_path))
    out = subprocess.run([str(_lint_imports()), "--config", str(ROOT / "pyproject.toml"), "--no-cache"],
                         cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-2000:]
    assert " 0 broken" in out.stdout, out.stdout[-2000:]
