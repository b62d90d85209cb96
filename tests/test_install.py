"""The installed package, as a user gets it: a wheel built from the sources, installed (not editable)
into a fresh virtual environment, run from a folder outside the repository.

This takes about a minute (building the wheel, and compiling the render kernels on a fresh machine);
CI runs it, because the failures it guards against (data files left out of the wheel, stray top-level
packages, the checkout shadowing the installed copy) never show in an editable install.
"""

import os
import shutil
import subprocess
import sys
import tomllib
import zipfile
from importlib import metadata
from pathlib import Path

import h5py
import pytest
from synthbos.raytrace import SETUPS

REPO = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())
WARP_NO_DRIVER = "Could not find or load the NVIDIA CUDA driver"

# A tiny render of the default set-up (the embedded buoyancy snapshot): few pixels, few rays.
TINY_TOML = """\
[camera]
pixels = [64, 64]
[target]
dots_per_32px = 8.0
[volume]
source = "slice"
[rays]
per_dot = 10
"""


def _clean_env():
    """The environment without anything that would put the checkout on the import path."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP")}
    env["PYTHONNOUSERSITE"] = "1"
    env["PIP_DISABLE_PIP_VERSION_CHECK"] = "1"
    return env


def _run(cmd, *, cwd, timeout=900):
    proc = subprocess.run([str(c) for c in cmd], cwd=cwd, env=_clean_env(), capture_output=True, text=True,
                          timeout=timeout)
    assert proc.returncode == 0, f"{' '.join(map(str, cmd))} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
    return proc


def _copy_sources(dest: Path) -> Path:
    """The files a wheel is built from (pyproject, README, the mapped package folders), without build
    leftovers, so a stale ``build/`` or ``*.egg-info`` in the checkout cannot leak into the wheel."""
    dest.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        if (REPO / name).is_file():
            shutil.copy2(REPO / name, dest / name)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.tmp")
    for folder in sorted(set(PYPROJECT["tool"]["setuptools"]["package-dir"].values())):
        shutil.copytree(REPO / folder, dest / folder, ignore=ignore)
    return dest


def _setuptools_is_recent() -> bool:
    try:
        return int(metadata.version("setuptools").split(".")[0]) >= 68 and bool(metadata.version("wheel"))
    except metadata.PackageNotFoundError:
        return False


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """A wheel built from a clean copy of the sources."""
    root = tmp_path_factory.mktemp("wheel")
    src = _copy_sources(root / "src")
    out = root / "dist"
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "-w", out, src]
    if _setuptools_is_recent():  # the build back end is here already: no download needed
        cmd.insert(4, "--no-build-isolation")
    _run(cmd, cwd=root)
    (whl,) = out.glob("synthbos-*.whl")
    return whl


def test_wheel_installs_only_the_synthbos_package(wheel):
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
        dist_info = next(n.split("/")[0] for n in names if n.split("/")[0].endswith(".dist-info"))
        assert dist_info.startswith("synthbos-")
        stray = [n for n in names if not (n.startswith("synthbos/") or n.startswith(f"{dist_info}/"))]
        assert stray == []
        if f"{dist_info}/top_level.txt" in names:
            assert z.read(f"{dist_info}/top_level.txt").decode().split() == ["synthbos"]
        # The package data travels with it: the default set-up, the embedded snapshots, the baseline.
        for data in ("synthbos/raytrace/default.toml", "synthbos/data/buoyancy_snapshots.h5",
                     "synthbos/data/baselines/regress.json", "synthbos/__main__.py"):
            assert data in names
        for file, _ in SETUPS.values():  # every named set-up
            assert f"synthbos/raytrace/{file}" in names


def test_installed_wheel_renders_from_another_folder(wheel, tmp_path):
    venv = tmp_path / "venv"
    # The dependencies (warp-lang, numpy, h5py, ...) come from the environment running the tests; the
    # editable install of the checkout there must not shadow the venv's own copy (checked below).
    # Without pip of its own (no ensurepip needed): this interpreter's pip installs into it.
    _run([sys.executable, "-m", "venv", "--system-site-packages", "--without-pip", venv], cwd=tmp_path)
    bindir = venv / ("Scripts" if os.name == "nt" else "bin")
    python = bindir / "python"
    _run([sys.executable, "-m", "pip", "--python", python, "install", "--no-deps", "--force-reinstall", "--quiet",
          wheel], cwd=tmp_path)
    work = tmp_path / "elsewhere"
    work.mkdir()

    where = _run([python, "-c", "import synthbos; print(synthbos.__file__)"], cwd=work).stdout.strip()
    assert Path(where).resolve().is_relative_to(venv.resolve()), where
    version = _run([python, "-m", "synthbos", "--version"], cwd=work).stdout.strip()
    assert version == f"synthbos {PYPROJECT['project']['version']}"

    (work / "tiny.toml").write_text(TINY_TOML)
    proc = _run([bindir / "synthbos", "render", "tiny.toml", "--setup", "narrow", "-o", "pair.h5", "--device", "cpu",
                 "-q"], cwd=work)
    assert WARP_NO_DRIVER not in proc.stderr
    assert proc.stdout.count("device: ") == 1
    with h5py.File(work / "pair.h5", "r") as f:
        assert f["images/reference"].shape == (64, 64)
        assert f["dots/displacement_px"].attrs["units"] == "px"
        assert 'source = "slice"' in f.attrs["config"]
        assert "f_number = 32.0" in f.attrs["config"]  # the named set-up, read from the installed package
