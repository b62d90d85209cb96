"""The README's Python quick start runs as written (its source: docs/quickstart.py, pasted into the README)."""

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
QUICKSTART = ROOT / "docs" / "quickstart.py"


def readme_quickstart():
    """The README's first ```python block when it is the quick start (it renders a pair), else None."""
    readme = ROOT / "README.md"
    if not readme.is_file():
        return None
    m = re.search(r"^```python\n(.*?)^```", readme.read_text(encoding="utf-8"), re.MULTILINE | re.DOTALL)
    if m is None or "render_pair" not in m.group(1):
        return None
    return m.group(1)


def _run(text, folder):
    script = folder / "quickstart.py"
    script.write_text(text, encoding="utf-8")
    run = subprocess.run([sys.executable, str(script)], cwd=folder, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    assert not run.stderr.strip(), run.stderr[-3000:]  # no warnings on the way
    assert list(folder.iterdir()) == [script]  # it writes nothing
    return run.stdout


def test_quickstart_is_short_and_python():
    text = QUICKSTART.read_text(encoding="utf-8")
    assert len(text.strip().splitlines()) <= 20
    ast.parse(text)


def test_quickstart_runs(tmp_path):
    out = _run(QUICKSTART.read_text(encoding="utf-8"), tmp_path)
    # the score it prints: tracking at 1 % noise on 128 x 128 px, p90 0.057 px measured
    score = ast.literal_eval(next(line for line in out.splitlines() if line.startswith("{'method'")))
    assert score["method"] == "tracking" and 0.02 < score["p90"] < 0.1 and score["yield"] > 0.95
    assert "dot_id" in out


def test_readme_quickstart_runs(tmp_path):
    block = readme_quickstart()
    if block is None or block.strip() == QUICKSTART.read_text(encoding="utf-8").strip():
        pytest.skip("the README's quick start is docs/quickstart.py, run above (or the README has none)")
    _run(block, tmp_path)
