"""The documentation: the site builds with ``mkdocs build --strict``, the configuration reference
documents every key the code has, and the README keeps its set-up commands and working links.

The build needs the ``docs`` extra (which the ``test`` extra carries). Without it the build test is
skipped on a developer's machine, but fails in CI (``CI`` set), so CI always builds the site.
"""

import dataclasses
import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SETUP_COMMANDS = (
    'pip install -e . && synthbos paper --quick\npip install -e ".[test]" && python3 -m pytest\n'
)


def _load_hooks():
    spec = importlib.util.spec_from_file_location("synthbos_docs_hooks", REPO / "docs" / "hooks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _need(module):
    if importlib.util.find_spec(module) is None:
        if os.environ.get("CI"):
            pytest.fail(f"{module} is not installed: the test extra must carry the docs extra")
        pytest.skip(f"{module} not installed (pip install -e '.[docs]')")


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The site built strictly into a temporary folder (run from there, so no cache lands in the checkout)."""
    _need("mkdocs")
    _need("mkdocstrings")
    _need("mkdocs_jupyter")
    root = tmp_path_factory.mktemp("site")
    out = root / "site"
    cmd = [sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(REPO / "mkdocs.yml"), "-d", str(out)]
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    run = subprocess.run(cmd, cwd=root, capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 0, f"mkdocs build --strict failed:\n{run.stdout}\n{run.stderr}"
    return out


def test_site_builds_strictly_with_every_page(site):
    nav = re.findall(r":\s*([\w-]+)\.(?:md|ipynb)\s*$", (REPO / "mkdocs.yml").read_text(), re.MULTILINE)
    assert len(nav) >= 14
    for page in nav:
        html = site / ("" if page == "index" else page) / "index.html"
        assert html.is_file(), f"{page} was not built"


def test_configuration_tables_come_from_the_code(site):
    from synthbos.correlation.multigrid import CorrelationSettings
    from synthbos.raytrace.config import DEFAULT_CONFIG
    from synthbos.tracking.pipeline import TrackingSettings

    html = (site / "configuration" / "index.html").read_text()
    assert "config-table" not in html
    f_number = DEFAULT_CONFIG["camera"]["f_number"]
    assert re.search(rf"<code>f_number</code></td>\s*<td><code>{f_number:g}</code>", html)
    for name, value in (("max_displacement", TrackingSettings().max_displacement),
                        ("peak_ratio_min", CorrelationSettings().peak_ratio_min)):
        assert re.search(rf"<code>{name}</code></td>\s*<td><code>{value:g}</code>", html), name


def test_api_reference_shows_the_main_functions(site):
    html = (site / "api" / "index.html").read_text()
    for name in ("synthbos.raytrace.render.render_pair", "synthbos.tracking.pipeline.track_pair",
                 "synthbos.correlation.multigrid.correlate_pair", "synthbos.integration.solvers.lsq_integrate"):
        assert f'id="{name}"' in html, name


def test_every_setting_has_a_description():
    assert _load_hooks().undocumented() == []


def test_settings_tables_read_defaults_ranges_and_descriptions():
    hooks = _load_hooks()
    from synthbos.tracking.pipeline import TRACKING_RANGES, TrackingSettings

    rows = {line.split(" | ")[0].strip("| `"): line.split(" | ") for line in hooks._tracking().splitlines()[2:]}
    assert set(rows) == {f.name for f in dataclasses.fields(TrackingSettings)}
    assert rows["fit_iterations"][1] == f"`{TrackingSettings().fit_iterations}`"
    bounds = TRACKING_RANGES["fit_iterations"]
    assert rows["fit_iterations"][3] == f"integer [{bounds['minimum']}, {bounds['maximum']}]"
    assert rows["diameter"][2] == "float or None" and rows["diameter"][1] == "unset"
    assert hooks.unit_of("camera.pixel_pitch_um") == "µm"
    assert hooks.unit_of("volume.gladstone_dale_m3_per_kg") == "m³/kg"


def test_readme_starts_with_the_two_set_up_commands_and_stays_short():
    text = (REPO / "README.md").read_text()
    first_block = re.search(r"```bash\n(.*?)```", text, re.DOTALL).group(1)
    assert first_block == SETUP_COMMANDS
    assert text.index("```bash") < text.index("```python")  # the set-up first, then the Python quick start
    assert len(text.splitlines()) <= 200


@pytest.mark.parametrize("name", ["README.md", "CHANGELOG.md"])
def test_relative_links_point_to_files(name):
    text = (REPO / name).read_text()
    links = [link.split("#")[0] for link in re.findall(r"\]\(([^)\s]+)\)", text) if "://" not in link]
    assert links
    missing = [link for link in links if link and not (REPO / link).exists()]
    assert missing == []


def test_license_is_the_declared_one():
    import tomllib

    declared = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["license"]["text"]
    assert declared == "BSD-3-Clause"
    assert (REPO / "LICENSE").read_text().startswith("BSD 3-Clause License")
