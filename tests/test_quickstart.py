"""The README's Python quick start runs as written (its source: docs/quickstart.py, pasted into the README)."""

import ast
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
QUICKSTART = ROOT / "docs" / "quickstart.py"


def readme_quickstart():
    """The README's first ```python block when it is the quick start (it imports synthbos), else None."""
    readme = ROOT / "README.md"
    if not readme.is_file():
        return None
    m = re.search(r"^```python\n(.*?)^```", readme.read_text(encoding="utf-8"), re.MULTILINE | re.DOTALL)
    if m is None or not re.search(r"^import synthbos$", m.group(1), re.MULTILINE):
        return None
    return m.group(1)


def snippets():
    """The quick start's texts to run: the file's, and the README's block when it differs from it."""
    texts = [QUICKSTART.read_text(encoding="utf-8")]
    block = readme_quickstart()
    if block is not None and block.strip() != texts[0].strip():
        texts.append(block)
    return texts


def test_quickstart_is_short_and_python():
    text = QUICKSTART.read_text(encoding="utf-8")
    assert len(text.strip().splitlines()) <= 20
    ast.parse(text)


def test_quickstart_runs(tmp_path):
    for text in snippets():
        script = tmp_path / "quickstart.py"
        script.write_text(text, encoding="utf-8")
        run = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True,
                             timeout=300)
        assert run.returncode == 0, run.stderr[-3000:]
        # the score it prints: tracking at 1 % noise on 128 x 128 px, p90 0.057 px measured
        score = ast.literal_eval(next(line for line in run.stdout.splitlines() if line.startswith("{'method'")))
        assert score["method"] == "tracking" and 0.02 < score["p90"] < 0.1 and score["yield"] > 0.95
        assert "dot_id" in run.stdout
        assert not run.stderr.strip(), run.stderr[-3000:]  # no warnings on the way
        assert list(tmp_path.iterdir()) == [script]  # it writes nothing
