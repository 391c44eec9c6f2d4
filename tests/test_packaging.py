"""The wheel: built from the tree, it holds one top-level import name (``adaptnav``) with
every package of the repository under it, and installed into a fresh virtual environment
it gives a working ``adaptnav`` command (what ``pipx install .`` does)."""
from __future__ import annotations

import os
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

pytestmark = pytest.mark.timeout(600)

REPO = Path(__file__).resolve().parents[1]
FOLDERS = ("fusion", "calibration", "sonar", "sim", "service")


def source_packages() -> set[str]:
    """Import names the repository's packages must have once installed."""
    names = {"adaptnav"}
    for folder in FOLDERS:
        for init in (REPO / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(REPO)
            names.add("adaptnav." + ".".join(rel.parts))
    return names


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    res = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(out), str(REPO)],
                         capture_output=True, text=True, timeout=500)
    assert res.returncode == 0, res.stderr[-2000:]
    (whl,) = out.glob("adaptnav-*.whl")
    return whl


def test_wheel_has_one_import_name_and_every_package(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names}
    assert {t for t in top if not t.endswith(".dist-info")} == {"adaptnav"}
    in_wheel = {n[:-len("/__init__.py")].replace("/", ".") for n in names if n.endswith("/__init__.py")}
    assert source_packages() <= in_wheel, f"packages missing from the wheel: {source_packages() - in_wheel}"
    assert any(n.startswith("adaptnav/sim/scenarios/") and n.endswith(".toml") for n in names)
    entry = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
    assert "adaptnav = adaptnav.service.cli:main" in zipfile.ZipFile(wheel).read(entry).decode()


def test_wheel_installs_into_a_fresh_venv_with_a_working_command(wheel, tmp_path):
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    res = subprocess.run([str(venv / "bin" / "pip"), "install", "-q", "--no-deps", "--no-index", str(wheel)],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    # run away from the source tree (its adaptnav/ would be imported from the cwd);
    # the dependencies come from this environment's site-packages (not adaptnav: it is
    # installed here in editable mode, through a finder that PYTHONPATH does not load)
    env = dict(os.environ, PYTHONPATH=sysconfig.get_paths()["purelib"])
    py = str(venv / "bin" / "python")
    where = subprocess.run([py, "-c", "import adaptnav; print(adaptnav.__file__)"], capture_output=True,
                           text=True, env=env, timeout=60, cwd=tmp_path)
    assert where.stdout.strip().startswith(str(venv)), where.stdout + where.stderr
    mods = subprocess.run([py, "-c", "import pkgutil, importlib, adaptnav\n"
                           "bad = []\n"
                           "for m in pkgutil.walk_packages(adaptnav.__path__, 'adaptnav.'):\n"
                           "    if m.name == 'adaptnav.__main__':\n        continue  # runs the command\n"
                           "    try:\n        importlib.import_module(m.name)\n"
                           "    except Exception as e:\n        bad.append(f'{m.name}: {e!r}')\n"
                           "print('\\n'.join(bad))"], capture_output=True, text=True, env=env, timeout=300, cwd=tmp_path)
    assert mods.returncode == 0 and mods.stdout.strip() == "", mods.stdout + mods.stderr[-2000:]
    version = subprocess.run([str(venv / "bin" / "adaptnav"), "--version"], capture_output=True, text=True,
                             env=env, timeout=60, cwd=tmp_path)
    assert version.returncode == 0 and version.stdout.strip() == "adaptnav 0.1.0", version.stderr
    helped = subprocess.run([str(venv / "bin" / "adaptnav"), "replay", "--help"], capture_output=True, text=True,
                            env=env, timeout=60, cwd=tmp_path)
    assert helped.returncode == 0 and "--report" in helped.stdout
