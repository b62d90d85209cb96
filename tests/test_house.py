"""The algorithm packages' size rules (issue 26, "a clean house"): no module over 900 lines and no function
body over 120 lines, so that each room and each step stays readable on its own."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("raytrace", "correlation", "tracking", "integration")
MAX_MODULE_LINES = 900
MAX_BODY_LINES = 120


def _sources():
    return sorted(p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py"))


def _body_lines(node) -> int:
    """Lines of a function's body after its docstring."""
    body = node.body
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
        if isinstance(body[0].value.value, str):
            body = body[1:]
    return 0 if not body else node.end_lineno - body[0].lineno + 1


@pytest.mark.parametrize("path", _sources(), ids=lambda p: str(p.relative_to(ROOT)))
def test_modules_and_function_bodies_are_short(path):
    text = path.read_text()
    assert len(text.splitlines()) <= MAX_MODULE_LINES, f"{path.name}: {len(text.splitlines())} lines"
    long = [
        f"{node.name} ({_body_lines(node)} lines)"
        for node in ast.walk(ast.parse(text))
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and _body_lines(node) > MAX_BODY_LINES
    ]
    assert not long, f"{path.name}: {', '.join(long)}"


def test_the_rule_sees_a_long_body():
    long = "def f():\n    '''doc'''\n" + "    x = 1\n" * (MAX_BODY_LINES + 1)
    assert _body_lines(ast.parse(long).body[0]) == MAX_BODY_LINES + 1
