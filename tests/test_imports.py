"""The package's import graph: arrows point one way (docs: STYLE, "Arrows point one way").

Every ``.py`` file of the package is parsed (not imported) and each ``import`` and ``from ... import``
statement, at module level or inside a function, becomes an edge from its module to the modules it
loads: the module named, a submodule named in the ``from`` list, and the packages above the target that
the importer is not itself inside (Python runs their ``__init__`` first). ``synthbos/__init__``'s lazy
public API (PEP 562 ``__getattr__`` through ``importlib.import_module``) is not an import statement, by
design: ``import synthbos`` stays cheap and the subpackages import it for ``SynthbosError``.
"""

import ast
import functools
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: Folder in the repository -> the package it installs as (pyproject.toml's package-dir).
FOLDERS = {
    "synthbos": "synthbos",
    "raytrace": "synthbos.raytrace",
    "correlation": "synthbos.correlation",
    "tracking": "synthbos.tracking",
    "integration": "synthbos.integration",
    "benchmarks": "synthbos.benchmarks",
}

#: Import circles among the benchmark modules that are known and left. The pair-file density step, the
#: processing step and the setup-table reader call each other, through imports inside functions:
#: ``integrate`` reads results (``process.read_result``) and setup tables; ``process`` reads the
#: geometry (``integrate.geometry_from_pair``, ``setup_attr``) and setup tables; ``setup_file`` builds an
#: ``integrate.Geometry`` and processes its tables (``process.process_tables``). Untangling them means
#: a lower module for the geometry and the result reader, shared by the three (left to the campaign work).
KNOWN_BENCHMARK_CIRCLES = [
    {"synthbos.benchmarks.integrate", "synthbos.benchmarks.process", "synthbos.benchmarks.setup_file"},
]


def _modules():
    """``{module name: (path, is_package)}`` of every .py file of the package."""
    out = {}
    for folder, package in FOLDERS.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = path.relative_to(ROOT / folder).with_suffix("").parts
            is_package = parts[-1] == "__init__"
            name = ".".join((package, *parts[:-1])) if is_package else ".".join((package, *parts))
            out[name] = (path, is_package)
    return out


def _resolve(name, modules):
    """The longest prefix of ``name`` that is a module of the package, or None (outside it)."""
    parts = name.split(".")
    for k in range(len(parts), 0, -1):
        candidate = ".".join(parts[:k])
        if candidate in modules:
            return candidate
    return None


def _targets(node, module, is_package, modules):
    """Modules of the package that one import statement of ``module`` names: the module imported, or
    for ``from base import names`` each name that is a submodule, and ``base`` itself unless every name
    is a submodule (then ``base`` only runs first, as the package above them)."""
    if isinstance(node, ast.Import):
        return [_resolve(alias.name, modules) for alias in node.names]
    if node.level:
        base = module.split(".") if is_package else module.split(".")[:-1]
        base = base[: len(base) - (node.level - 1)]
        base = ".".join(base + ([node.module] if node.module else []))
    else:
        base = node.module
    subs = [f"{base}.{alias.name}" for alias in node.names if f"{base}.{alias.name}" in modules]
    return subs if len(subs) == len(node.names) else [_resolve(base, modules), *subs]


def _lazy_api_nodes(tree):
    """Import statements inside ``__getattr__`` (the lazy public API of ``synthbos/__init__``)."""
    skip = set()
    for node in tree.body:
        if isinstance(node, ast.FunctionDef) and node.name == "__getattr__":
            skip |= {id(n) for n in ast.walk(node)}
    return skip


@functools.cache
def import_graph():
    """``{module: set of modules it imports}`` over the whole package (do not change the result)."""
    modules = _modules()
    graph = {}
    for module, (path, is_package) in modules.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        skip = _lazy_api_nodes(tree) if module == "synthbos" else set()
        own = {".".join(module.split(".")[:k]) for k in range(1, module.count(".") + 2)}
        edges = set()
        for node in ast.walk(tree):
            if not isinstance(node, (ast.Import, ast.ImportFrom)) or id(node) in skip:
                continue
            for target in _targets(node, module, is_package, modules):
                if target is None:
                    continue
                parts = target.split(".")
                # the target, and the packages above it that the importer is not already inside
                edges |= {target} | ({".".join(parts[:k]) for k in range(1, len(parts))} - own)
        graph[module] = edges & set(modules)
    return graph


def circles(graph):
    """Strongly connected components with more than one module (Tarjan), each a sorted tuple."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(tuple(sorted(component)))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _package(module):
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in FOLDERS else "synthbos"


def test_the_graph_sees_imports_inside_functions_and_relative_ones():
    graph = import_graph()
    # a relative import at module level, one of a submodule by name, and one inside a function
    assert "synthbos.tracking.settings" in graph["synthbos.tracking.kernel_constants"]
    assert "synthbos.correlation.pass_kernels" in graph["synthbos.correlation.device_pass"]
    assert "synthbos.benchmarks.cli" in graph["synthbos.__main__"]
    # an absolute import of another subpackage loads that package's __init__ too
    assert {"synthbos.correlation", "synthbos.correlation.windows"} <= graph["synthbos.tracking.mask"]
    # the lazy public API is not an import; the errors module is
    assert not any(m.startswith("synthbos.tracking") for m in graph["synthbos"])
    assert "synthbos.errors" in graph["synthbos"]
    # an attribute of the importer's own package is an import of that package's __init__
    assert "synthbos" in graph["synthbos.values"]  # from synthbos import SynthbosError
    # a circle drawn on purpose is found
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [("a", "b", "c")]


def test_no_import_circle_in_the_algorithm_packages_or_the_base():
    found = [c for c in circles(import_graph()) if any(_package(m) != "benchmarks" for m in c)]
    assert found == []


def test_benchmark_circles_are_only_the_known_ones():
    found = [set(c) for c in circles(import_graph()) if all(_package(m) == "benchmarks" for m in c)]
    assert sorted(map(sorted, found)) == sorted(map(sorted, KNOWN_BENCHMARK_CIRCLES))


@pytest.mark.parametrize(
    ("importer", "forbidden"),
    [
        ("correlation", {"tracking", "raytrace", "integration", "benchmarks"}),
        ("tracking", {"raytrace", "integration", "benchmarks"}),
        ("integration", {"raytrace", "tracking", "correlation", "benchmarks"}),
        ("raytrace", {"tracking", "correlation", "integration", "benchmarks"}),
    ],
)
def test_arrows_point_one_way(importer, forbidden):
    graph = import_graph()
    wrong = sorted(
        (m, t) for m, targets in graph.items() if _package(m) == importer for t in targets if _package(t) in forbidden
    )
    assert wrong == []


def test_the_kernel_modules_import_the_vocabulary_not_the_orchestrator():
    graph = import_graph()
    for kernels in (
        "claim_kernels",
        "deform_kernels",
        "ellipse_kernels",
        "fit_kernels",
        "identify_kernels",
        "kernel_constants",
        "kernel_step_kernels",
        "moment_kernels",
        "neighbour_kernels",
        "predict_fft_kernels",
        "predict_kernels",
        "stats_kernels",
        "table_kernels",
        "wide_search_kernels",
    ):
        assert "synthbos.tracking.pipeline" not in graph[f"synthbos.tracking.{kernels}"]
    assert not (graph["synthbos.tracking.settings"] - {"synthbos", "synthbos.errors", "synthbos.values"})


def test_no_production_module_imports_the_tracking_reference():
    """The NumPy references (``tracking/reference.py``) are for the tests: no module of the package loads
    them, and they are there to be loaded (the test would pass vacuously if the module were renamed)."""
    graph = import_graph()
    reference = "synthbos.tracking.reference"
    assert reference in graph
    assert {"synthbos.tracking.dotfit", "synthbos.tracking.register"} <= graph[reference]
    importers = sorted(module for module, edges in graph.items() if reference in edges)
    assert importers == []
    kernel = "synthbos.tracking.reference_kernel"  # the shared-kernel step's, loaded by the reference only
    assert kernel in graph[reference]
    assert sorted(module for module, edges in graph.items() if kernel in edges) == [reference]


def test_the_command_line_loads_without_matplotlib():
    """A command's process imports matplotlib only where it draws (``campaign.draw_figure`` in the workers,
    the plotting commands): it took 0.6 s of every command's start on an H200's host."""
    code = "import sys, synthbos.benchmarks.cli, synthbos.benchmarks.campaign; print('matplotlib' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
    from synthbos.benchmarks.campaign import draw_figure

    assert draw_figure.preload == "synthbos.benchmarks.figures"  # the workers import it ahead
