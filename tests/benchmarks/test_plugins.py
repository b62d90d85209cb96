"""Method plugins through the ``synthbos.methods`` entry points: discovery, skipped plugins, every command.

The plugins here are real distributions as far as ``importlib.metadata`` is concerned: a folder on
``sys.path`` holding their modules and a ``*.dist-info`` with ``METADATA`` and ``entry_points.txt``
(what pip writes). ``test_example_plugin.py`` installs the example plugin with pip instead.
"""

import shutil
import textwrap
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose
from synthbos.benchmarks import registry, scoring
from synthbos.benchmarks.campaign import run_campaign
from synthbos.benchmarks.cli import main
from synthbos.benchmarks.items import score_result
from synthbos.benchmarks.method_api import DENSE, Method, dense_result
from synthbos.benchmarks.plugins import PluginWarning
from synthbos.benchmarks.process import read_result
from synthbos.benchmarks.regress import run_regress
from synthbos.benchmarks.spec import REGRESS
from synthbos.raytrace import read_pair, render_pair, write_pair

from synthbos import SynthbosError

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "phasecorr" / "synthbos_phasecorr.py"
TINY_CONFIG = {"camera": {"pixels": [128, 128]}, "rays": {"per_dot": 20}}
TINY = replace(REGRESS, name="tiny-plugins", snapshots=(2,), noise_percent=(0.0, 3.0), config=TINY_CONFIG)

# Fake plugins: a method that measures nothing (zero displacement) of each kind the harness scores
# against interpolated or sampled truth, and faulty ones.
ZERO = '''
from dataclasses import dataclass
import numpy as np
from synthbos.benchmarks.method_api import DENSE, DOTS, Method, dense_result, dots_result

@dataclass(frozen=True)
class Nothing:
    step: int = 16

def run_dense(reference, gradient, *, prior_xy=None, settings=None, device=None, mask=None):
    return dense_result("zero-dense", np.zeros(reference.shape), np.zeros(reference.shape), settings=settings)

def run_dots(reference, gradient, *, prior_xy=None, settings=None, device=None, mask=None):
    y, x = np.mgrid[8:reference.shape[0]:settings.step, 8:reference.shape[1]:settings.step].astype(float)
    return dots_result("zero-dots", x + 0.3, y + 0.6, 0 * x, 0 * y, settings=settings)

DENSE_METHOD = Method("zero-dense", DENSE, Nothing, run_dense, label="zero field", color="#56B4E9",
                      linestyle="--", marker="x")

def dots_method():
    return Method("zero-dots", DOTS, Nothing, run_dots, label="zero at a lattice", color="tab:olive",
                  linestyle=":", marker="+")
'''
FAULTY = '''
from dataclasses import dataclass
import numpy as np
from synthbos.benchmarks.method_api import GRID, Method, dots_result

@dataclass(frozen=True)
class S:
    pass

def run(reference, gradient, *, prior_xy=None, settings=None, device=None, mask=None):
    return dots_result("wrong-result", np.zeros(4), np.zeros(4), np.zeros(4), np.zeros(4))  # a grid method

def style(**kw):
    return Method(**{"name": "x", "kind": GRID, "settings_class": S, "run": run, "label": "x", "color": "k",
                     "linestyle": "-", "marker": "o", **kw})

BAD_KIND = style(name="bad-kind", kind="volume")
BAD_COLOUR = style(name="bad-colour", color="not a colour")
TAKEN = style(name="correlation")
MISNAMED = style(name="other-name")
WRONG_RESULT = style(name="wrong-result")
'''


def _distribution(root: Path, name: str, modules: dict, entry_points: dict) -> None:
    """A distribution as pip installs it: modules and ``{name}-1.0.dist-info`` in ``root``."""
    for module, source in modules.items():
        (root / f"{module}.py").write_text(textwrap.dedent(source))
    info = root / f"{name.replace('-', '_')}-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 1.0\n")
    lines = "".join(f"{k} = {v}\n" for k, v in entry_points.items())
    (info / "entry_points.txt").write_text(f"[synthbos.methods]\n{lines}")


@pytest.fixture
def plugins(tmp_path, monkeypatch):
    """Good plugins (the example's phase correlation, the zero methods) and faulty ones on ``sys.path``."""
    root = tmp_path / "site"
    root.mkdir()
    shutil.copy(EXAMPLE, root / EXAMPLE.name)
    _distribution(root, "synthbos-phasecorr", {}, {"phase-correlation": "synthbos_phasecorr:METHOD"})
    _distribution(root, "zero-methods", {"zero_methods": ZERO},
                  {"zero-dense": "zero_methods:DENSE_METHOD", "zero-dots": "zero_methods:dots_method"})
    _distribution(root, "faulty-methods", {"faulty_methods": FAULTY, "broken_import": "import no_such_module\n"},
                  {"broken-import": "broken_import:METHOD", "bad-kind": "faulty_methods:BAD_KIND",
                   "bad-colour": "faulty_methods:BAD_COLOUR", "correlation": "faulty_methods:TAKEN",
                   "misnamed": "faulty_methods:MISNAMED", "wrong-result": "faulty_methods:WRONG_RESULT"})
    monkeypatch.syspath_prepend(str(root))
    registry.forget_plugins()
    yield root
    registry.forget_plugins()


SKIPPED = {"broken-import": "No module named 'no_such_module'", "bad-kind": "kind 'volume' is not one of",
           "bad-colour": "is not a matplotlib colour", "correlation": "is taken",
           "misnamed": "the entry point is named 'misnamed' but its method 'other-name'"}


def test_listing_skips_each_faulty_plugin_with_one_warning_and_keeps_the_rest(plugins):
    with pytest.warns(PluginWarning) as caught:
        names = registry.method_names()
    assert names[: len(registry.BUILT_IN)] == tuple(registry.BUILT_IN)
    assert set(names) - set(registry.BUILT_IN) == {"phase-correlation", "zero-dense", "zero-dots", "wrong-result"}
    messages = [str(w.message) for w in caught]
    assert len(messages) == len(SKIPPED)
    for name, reason in SKIPPED.items():
        (line,) = [m for m in messages if m.startswith(f"method plugin {name!r} (faulty-methods 1.0) skipped: ")]
        assert reason in line and "\n" not in line
    m = registry.get_method("phase-correlation")
    assert m.source == "synthbos-phasecorr 1.0" and not m.in_default_campaign
    assert registry.get_method("correlation").source.startswith("synthbos ")  # the built-in one stays
    assert registry.default_methods() == ("correlation", "tracking", "tracking-cc")
    with pytest.raises(SynthbosError, match="No module named 'no_such_module'"):
        registry.get_method("broken-import")


def test_a_named_plugin_loads_alone(plugins, recwarn):
    assert registry.get_method("zero-dense").kind == DENSE
    assert registry.get_method("correlation").kind == "grid"
    assert not [w for w in recwarn if issubclass(w.category, PluginWarning)]  # the faulty ones were not loaded


def test_cli_lists_methods_and_reports_skipped_plugins_on_one_line_each(plugins, capsys):
    assert main(["methods"]) == 0
    out, err = capsys.readouterr()
    row = next(line for line in out.splitlines() if line.startswith("phase-correlation "))
    assert row.split()[1:5] == ["grid", "no", "synthbos-phasecorr", "1.0"]
    assert "optical-flow" in out and "openpiv" in out
    warned = [line for line in err.splitlines() if line.startswith("synthbos: warning: method plugin")]
    assert len(warned) == len(SKIPPED) == len(err.strip().splitlines())


@pytest.mark.filterwarnings("ignore::synthbos.benchmarks.plugins.PluginWarning")
def test_a_wrong_result_is_one_line_naming_the_method(plugins, tmp_path, capsys):
    pair = tmp_path / "pair.h5"
    write_pair(pair, render_pair(TINY.pair_config(2, 0), device="cpu"))
    assert main(["process", str(pair), "--method", "wrong-result", "-o", str(tmp_path / "r.h5")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "synthbos: error: method 'wrong-result' returned grid_shape None for 4 points"
    assert not (tmp_path / "r.h5").exists()
    assert main(["process", str(pair), "--method", "broken-import", "-o", str(tmp_path / "r.h5")]) == 2
    assert "No module named 'no_such_module'" in capsys.readouterr().err


def test_dense_and_scattered_plugins_are_scored_against_sampled_and_interpolated_truth(plugins, tmp_path):
    """A method that measures zero everywhere has, at each scored point, the truth's magnitude as its error."""
    path = tmp_path / "pair.h5"
    write_pair(path, render_pair(TINY.pair_config(2, 0), device="cpu"))
    pair = read_pair(path)
    img = np.zeros(pair.reference.shape)
    ok = pair.valid & np.all(np.isfinite(pair.displacement_px), axis=1)

    dense = registry.get_method("zero-dense").run(img, img, settings=registry.get_method("zero-dense").settings())
    sc = score_result(pair, "zero-dense", dense)
    assert_allclose(sc["error"], np.hypot(*pair.displacement_px[ok].T), rtol=1e-12)
    assert sc["measured"] == sc["expected"] == ok.sum()

    m = registry.get_method("zero-dots")
    dots = m.run(img, img, settings=m.settings({"step": 8}))
    sc = score_result(pair, "zero-dots", dots)
    truth = scoring.interpolate_truth(pair.reference_px[ok], pair.displacement_px[ok], dots.xy)
    inside = np.all(np.isfinite(truth), axis=1)
    assert_allclose(sc["error"], np.hypot(*truth[inside].T), rtol=1e-12)
    assert sc["density_error_cone"].size > 0  # integrated too


def test_sample_field_is_bilinear_and_exact_for_a_linear_field():
    rng = np.random.default_rng(3)
    y, x = np.mgrid[0:40, 0:50].astype(float)
    field = np.stack([0.3 + 0.01 * x - 0.02 * y, -0.1 + 0.005 * x * 1 + 0.03 * y], axis=-1)
    pts = np.column_stack([rng.uniform(0, 49, 200), rng.uniform(0, 39, 200)])
    expect = np.column_stack([0.3 + 0.01 * pts[:, 0] - 0.02 * pts[:, 1], -0.1 + 0.005 * pts[:, 0] + 0.03 * pts[:, 1]])
    assert_allclose(scoring.sample_field(field, pts), expect, atol=1e-12)
    assert np.isnan(scoring.sample_field(field, np.array([[49.6, 3.0], [2.0, -0.6]]))).all()
    assert_allclose(scoring.sample_field(field, np.array([[49.4, -0.4]])), field[[0], [49]], atol=1e-12)
    holed = field.copy()
    holed[10, 10] = np.nan
    got = scoring.sample_field(holed, np.array([[10.5, 9.5], [12.5, 12.5]]))
    assert np.isnan(got[0]).all() and np.isfinite(got[1]).all()


@pytest.mark.filterwarnings("ignore::synthbos.benchmarks.plugins.PluginWarning")
def test_plugins_run_through_a_campaign_with_figures_and_process_integrate_show(plugins, tmp_path, capsys):
    spec = replace(TINY, methods=("correlation", "phase-correlation", "zero-dense"))
    rows = run_campaign(spec, tmp_path / "c", device="cpu", workers=1, progress=False)
    p90 = {(r["method"], r["noise_percent"]): r["p90"] for r in rows if r["split"] == "all"
           and r["quantity"] == "displacement"}
    for noise in spec.noise_percent:
        assert 0 < p90[("phase-correlation", noise)] < 0.3  # a real measurement of a ~0.1 px field
        assert p90[("correlation", noise)] < p90[("zero-dense", noise)]
    for stem in ("fig4", "fig5", "fig_density"):
        assert (tmp_path / "c" / f"{stem}.png").stat().st_size > 10_000
    pair, result = tmp_path / "c" / "pairs" / "s2_p00.h5", tmp_path / "r.h5"
    assert main(["process", str(pair), "--method", "phase-correlation", "-o", str(result)]) == 0
    res, attrs = read_result(result)
    assert attrs["kind"] == "grid" and res.grid_shape == (7, 7)
    config = tmp_path / "process.toml"  # the plugin's own table of a process configuration
    config.write_text("[phase-correlation]\nwindow = 64\nstep = 32\n")
    assert main(["process", str(pair), "--method", "phase-correlation", "--config", str(config), "-o",
                 str(tmp_path / "r64.h5")]) == 0
    assert read_result(tmp_path / "r64.h5")[0].grid_shape == (3, 3)
    assert main(["integrate", str(result), "--pair", str(pair), "-o", str(tmp_path / "d.h5")]) == 0
    assert main(["show-result", str(result), "-o", str(tmp_path / "r.png")]) == 0
    assert main(["process", str(pair), "--method", "zero-dense", "-o", str(tmp_path / "z.h5")]) == 0
    dense, _ = read_result(tmp_path / "z.h5")
    assert dense.grid_shape == (128, 128) and np.all(dense.uv == 0)
    assert main(["integrate", str(tmp_path / "z.h5"), "--pair", str(pair), "-o", str(tmp_path / "dz.h5")]) == 0
    assert main(["show-result", str(tmp_path / "z.h5"), "-o", str(tmp_path / "z.png")]) == 0


@pytest.mark.filterwarnings("ignore::synthbos.benchmarks.plugins.PluginWarning")
def test_regress_adds_a_plugins_rows_to_a_baseline_only_when_asked(plugins, tmp_path, monkeypatch):
    monkeypatch.setattr("synthbos.benchmarks.regress.REGRESS", replace(TINY, noise_percent=(3.0,)))
    base = tmp_path / "baseline.json"
    run_regress(update=True, baseline=base, progress=False, workers=1, methods=("correlation",))
    rows, problems = run_regress(baseline=base, progress=False, workers=1, methods=("phase-correlation",))
    assert problems and all("not in the baseline" in p for p in problems)
    run_regress(update=True, baseline=base, progress=False, workers=1, methods=("phase-correlation",))
    rows, problems = run_regress(baseline=base, progress=False, workers=1,
                                 methods=("correlation", "phase-correlation"))
    assert problems == [] and {r["method"] for r in rows} == {"correlation", "phase-correlation"}


@pytest.mark.filterwarnings("ignore::synthbos.benchmarks.plugins.PluginWarning")
def test_sweep_runs_the_named_methods_only(plugins, tmp_path):
    from synthbos.benchmarks.sweep import run_sweep

    rows = run_sweep({"camera": {"pixels": [96, 96]}, "rays": {"per_dot": 10}}, [("noise", [0.0, 3.0])],
                     tmp_path / "s", methods=("phase-correlation",), workers=1, progress=False)
    assert {r["method"] for r in rows} == {"phase-correlation"}
    assert {r["param_value"] for r in rows} == {0.0, 3.0}
    assert (tmp_path / "s" / "sweep.png").is_file()


def test_check_method_refuses_a_run_without_the_harness_keywords():
    from synthbos.benchmarks.method_api import check_method

    def run(reference, gradient):
        return None

    m = Method("no-keywords", DENSE, registry.BUILT_IN["optical-flow"].settings_class, run, label="x", color="k",
               linestyle="-", marker="o")
    with pytest.raises(SynthbosError, match="does not fit"):
        check_method(m)
    good = replace(m, run=lambda reference, gradient, **kw: dense_result("no-keywords", reference, reference))
    check_method(good)
