"""The example plugin (``examples/phasecorr``) installed with pip into a fresh virtual environment.

The environment sees this one's site directories, in this one's order (synthbos and its dependencies,
through a ``.pth`` file), and gets the plugin from pip, so its entry point is found the way a user's
would be. A few seconds: pip
builds the example's wheel without build isolation. The whole ``paper --quick`` with the plugin takes
minutes on two cores and runs with ``-m slow``.
"""

import json
import os
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import pytest
from synthbos.benchmarks.spec import REGRESS
from synthbos.raytrace import render_pair, write_pair

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "examples" / "phasecorr"
METHOD_CODE_LINES = 40  # the bound on the example's method code


def _env():
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP")}
    env["PYTHONNOUSERSITE"] = "1"
    env["PIP_DISABLE_PIP_VERSION_CHECK"] = "1"
    return env


def _run(cmd, *, cwd, timeout=900):
    proc = subprocess.run([str(c) for c in cmd], cwd=cwd, env=_env(), capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{' '.join(map(str, cmd))} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
    return proc


@pytest.fixture(scope="module")
def plugin_python(tmp_path_factory) -> Path:
    """The Python of a fresh venv that has this environment's packages and the example plugin, installed by pip."""
    root = tmp_path_factory.mktemp("plugin-venv")
    venv = root / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", venv], cwd=root)
    python = venv / ("Scripts" if os.name == "nt" else "bin") / "python"
    where = _run([python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"], cwd=root)
    # this environment's site directories, first to last (with their .pth files: an editable synthbos)
    parents = list(dict.fromkeys(p for p in sys.path if Path(p).name in ("site-packages", "dist-packages")))
    pth = Path(where.stdout.strip()) / "parent_env.pth"
    pth.write_text(f"import site; list(map(site.addsitedir, {parents!r}))\n")
    cmd = [sys.executable, "-m", "pip", "--python", python, "install", "--no-deps", "--quiet", EXAMPLE]
    if _can_build_here():  # else pip fetches the build back end (setuptools) into an isolated build
        cmd.insert(-1, "--no-build-isolation")
    _run(cmd, cwd=root)
    return python


def _can_build_here() -> bool:
    """Whether setuptools and wheel are here to build the example's wheel without downloading them."""
    try:
        return int(metadata.version("setuptools").split(".")[0]) >= 61 and bool(metadata.version("wheel"))
    except metadata.PackageNotFoundError:
        return False


def test_example_method_code_is_short():
    """Under 40 lines of method code: the module without its docstring, comments and blank lines."""
    lines = (EXAMPLE / "synthbos_phasecorr.py").read_text().split('"""', 2)[2].splitlines()
    code = [line for line in lines if line.strip() and not line.strip().startswith("#")]
    assert len(code) < METHOD_CODE_LINES, len(code)


def test_installed_plugin_is_listed_and_processes_a_pair(plugin_python, tmp_path):
    where = _run([plugin_python, "-c", "import synthbos_phasecorr as m; print(m.__file__)"], cwd=tmp_path).stdout
    assert "site-packages" in where and str(EXAMPLE) not in where  # the installed copy, not the example folder
    listing = _run([plugin_python, "-m", "synthbos", "methods"], cwd=tmp_path)
    row = next(line for line in listing.stdout.splitlines() if line.startswith("phase-correlation "))
    assert row.split()[1:5] == ["grid", "no", "synthbos-phasecorr", "0.1.0"]
    assert "warning" not in listing.stderr
    pair = tmp_path / "pair.h5"
    write_pair(pair, render_pair({**REGRESS.config, "camera": {"pixels": [128, 128]}, "rays": {"per_dot": 20}},
                                 device="cpu"))
    out = _run([plugin_python, "-m", "synthbos", "process", pair, "--method", "phase-correlation", "-o",
                tmp_path / "r.h5", "--device", "cpu"], cwd=tmp_path).stdout
    assert "phase-correlation, 49 vectors: 49 measured" in out
    _run([plugin_python, "-m", "synthbos", "integrate", tmp_path / "r.h5", "--pair", pair, "-o", tmp_path / "d.h5"],
         cwd=tmp_path)


@pytest.mark.slow
def test_installed_plugin_runs_through_paper_quick(slow_only, plugin_python, tmp_path):
    out = tmp_path / "paper"
    _run([plugin_python, "-m", "synthbos", "paper", "--quick", "--methods", "correlation,phase-correlation",
          "--out", out, "-q"], cwd=tmp_path, timeout=3600)
    rows = json.loads((out / "results.json").read_text())
    p90 = [r["p90"] for r in rows if r["method"] == "phase-correlation" and r["quantity"] == "displacement"
           and r["split"] == "all"]
    assert len(p90) == 4 and all(0 < v < 0.3 for v in p90)
    for stem in ("fig4", "fig5", "fig_density"):
        assert (out / f"{stem}.png").stat().st_size > 10_000 and (out / f"{stem}.pdf").is_file()
