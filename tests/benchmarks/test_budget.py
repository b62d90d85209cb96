"""The error budget: errors split by each dot's in-cone spread, in results.csv and in fig_budget.

The renderer's pairs get a synthesised ray covariance whose spread is a known linear function of the
dot's image position, so the spread at every scored point (dots, and window centres by interpolation)
and each bin's counts and percentiles are known exactly.
"""

import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal
from synthbos.benchmarks import figures, items, scoring
from synthbos.benchmarks.campaign import run_campaign, write_summary
from synthbos.benchmarks.cli import main
from synthbos.benchmarks.registry import GRID, get_method
from synthbos.benchmarks.spec import REGRESS
from synthbos.benchmarks.storage import SCORE_FIELDS, load_scores, pair_path, score_path
from synthbos.raytrace import read_pair
from synthbos.raytrace.pairfile import Pair, in_cone_spread_px

TINY = replace(
    REGRESS,
    name="tiny-budget",
    snapshots=(2,),
    noise_percent=(0.0, 3.0),
    config={"camera": {"pixels": [96, 96]}, "target": {"dots_per_32px": 12.0}, "rays": {"per_dot": 10}},
)
OLD_COLUMNS = ["method", "noise_percent", "split", "quantity", "n", "yield", "p50", "p68", "p90", "p95", "p99",
               "rms", "process_device"]
REF_TRACE = 0.02  # px^2: the reference image's ray covariance trace, subtracted by in_cone_spread_px


def linear_spread(xy):
    """The synthesised in-cone spread (px): 0.01 px at column 0 to 0.73 px at column 96, all four bins."""
    return 0.01 + 0.0075 * xy[:, 0]


def _with_covariance(render):
    """``render_pair`` whose pairs carry a ray covariance giving ``linear_spread``."""

    def with_covariance(config, device=None):
        pair = render(config, device=device)
        s2 = linear_spread(pair.reference_px) ** 2
        half = REF_TRACE / 2
        pair.ray_covariance_px2 = np.stack([0.3 * s2 + half, 0.7 * s2 + half, 0.1 * s2], axis=1)
        pair.ray_covariance_reference_px2 = np.tile([half, half, 0.0], (pair.n_dots, 1))
        return pair

    return with_covariance


@pytest.fixture(scope="module")
def spread_campaign(tmp_path_factory):
    """A tiny campaign whose pairs carry a ray covariance giving ``linear_spread``."""
    mp = pytest.MonkeyPatch()
    mp.setattr(items, "render_pair", _with_covariance(items.render_pair))
    folder = tmp_path_factory.mktemp("budget")
    try:
        rows = run_campaign(TINY, folder, device="cpu", workers=1, progress=False)
    finally:
        mp.undo()
    return folder, rows


def test_sweep_draws_its_budget(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(items, "render_pair", _with_covariance(items.render_pair))
    cfg = tmp_path / "base.toml"
    cfg.write_text('[camera]\npixels = [96, 96]\n[rays]\nper_dot = 10\n[target]\ndots_per_32px = 12.0\n')
    out = tmp_path / "sweep"
    assert main(["sweep", str(cfg), "--param", "f_number=11,16", "--param", "noise=0", "--out", str(out),
                 "--workers", "1", "-q", "--device", "cpu"]) == 0
    assert "not drawn" not in capsys.readouterr().out
    for fmt in ("png", "pdf"):
        assert (out / f"sweep_budget.{fmt}").stat().st_size > 10_000


def test_spread_bins_and_interpolation():
    masks = scoring.spread_bin_masks([0.0, 0.049, 0.05, 0.19, 0.2, 0.5, 3.0, np.nan])
    assert_array_equal(masks["undistorted"], [1, 1, 0, 0, 0, 0, 0, 0])
    assert_array_equal(masks["mild"], [0, 0, 1, 1, 0, 0, 0, 0])
    assert_array_equal(masks["distorted"], [0, 0, 0, 0, 1, 0, 0, 0])
    assert_array_equal(masks["strong"], [0, 0, 0, 0, 0, 1, 1, 0])
    rng = np.random.default_rng(0)
    dots = rng.uniform(0, 50, (200, 2))
    pts = np.array([[25.0, 25.0], [10.0, 40.0], [-5.0, 3.0]])
    out = scoring.interpolate_dots(dots, 0.2 + 0.01 * dots[:, 0] - 0.002 * dots[:, 1], pts)
    assert_allclose(out[:2], 0.2 + 0.01 * pts[:2, 0] - 0.002 * pts[:2, 1], rtol=1e-12)
    assert np.isnan(out[2])  # outside the hull
    assert np.isnan(scoring.interpolate_dots(dots[:2], [1.0, 2.0], pts)).all()


def test_in_cone_spread_of_a_pair():
    pair = Pair(
        reference=np.zeros((4, 4)), gradient=np.zeros((4, 4)), target_xy_m=np.zeros((3, 2)),
        reference_px=np.zeros((3, 2)), gradient_px=np.zeros((3, 2)), displacement_px=np.zeros((3, 2)),
        theory_px=np.zeros((3, 2)), valid=np.ones(3, bool))
    assert np.isnan(in_cone_spread_px(pair)).all()  # a pair from before the covariance
    pair.ray_covariance_px2 = np.array([[0.09, 0.16, 0.05], [0.01, 0.0, 0.0], [np.nan, 0.0, 0.0]])
    pair.ray_covariance_reference_px2 = np.zeros((3, 3))
    assert_allclose(in_cone_spread_px(pair)[:2], [0.5, 0.1])
    pair.ray_covariance_reference_px2 = np.array([[0.05, 0.04, 0.0], [0.02, 0.0, 0.0], [0.0, 0.0, 0.0]])
    assert_allclose(in_cone_spread_px(pair)[:2], [0.4, 0.0])  # more spread in the reference: none added
    assert np.isnan(in_cone_spread_px(pair)[2])


def test_scores_carry_the_spread_of_each_point(spread_campaign):
    folder, _ = spread_campaign
    pair = read_pair(pair_path(folder, 2, 0))
    valid = pair.valid & np.all(np.isfinite(pair.displacement_px), axis=1)
    for method in TINY.methods:
        with np.load(score_path(folder, 2, 0, 0.0, method)) as z:
            spread, n = z["spread"], len(z["error"])
        assert len(spread) == n
        if get_method(method).kind == GRID:
            # window centres: the dots' spreads interpolated linearly, exact for a linear spread
            res = items.measure_pair(pair, method, noise_percent=0.0, device="cpu")
            truth = scoring.interpolate_truth(pair.reference_px[valid], pair.displacement_px[valid], res.xy)
            centres = res.xy[np.all(np.isfinite(truth), axis=1)]
            assert_allclose(spread, linear_spread(centres), rtol=1e-9)
        else:
            assert_allclose(spread, linear_spread(pair.reference_px[valid]), rtol=1e-9)


def test_results_table_splits_errors_by_spread(spread_campaign):
    folder, rows = spread_campaign
    header = (folder / "results.csv").read_text().splitlines()[0].split(",")
    assert header[: len(OLD_COLUMNS)] == OLD_COLUMNS  # old readers keep working
    names = [b[0] for b in scoring.SPREAD_BINS]
    assert header[len(OLD_COLUMNS):] == [*(c for b in names for c in (f"n_{b}", f"p50_{b}", f"p90_{b}", f"p99_{b}")),
                                         "error_units"]
    for method in TINY.methods:
        for noise in TINY.noise_percent:
            sc = load_scores(TINY, folder, method, noise)
            above = sc["true_mag"] >= sc["threshold"]
            for split, sel in (("all", np.ones_like(above)), ("above", above)):
                row = next(r for r in rows if (r["method"], r["noise_percent"], r["split"], r["quantity"])
                           == (method, noise, split, "displacement"))
                e, s = sc["error"][sel], sc["spread"][sel]
                assert sum(row[f"n_{b}"] for b in names) == np.sum(np.isfinite(e) & np.isfinite(s))
                for name, lo, hi in scoring.SPREAD_BINS:
                    inside = e[(s >= lo) & (s < hi) & np.isfinite(e)]
                    assert row[f"n_{name}"] == len(inside)
                    if len(inside):
                        assert_allclose(row[f"p90_{name}"], np.percentile(inside, 90), rtol=1e-12)
                    else:
                        assert row[f"p50_{name}"] is None
            dens = next(r for r in rows if r["method"] == method and r["quantity"] == "density_cone_rel"
                        and r["noise_percent"] == noise)
            assert all(dens[f"n_{b}"] == 0 and dens[f"p90_{b}"] is None for b in names)
    tracked = next(r for r in rows if (r["method"], r["noise_percent"], r["split"], r["quantity"])
                   == ("tracking", 0.0, "all", "displacement"))
    assert all(tracked[f"n_{b}"] > 0 for b in names)  # the synthesised spread reaches every bin


def test_scores_loaded_field_by_field_are_the_whole_loads(spread_campaign):
    """A figure reads only the arrays it draws (``load_scores(fields=...)``): each is the whole load's."""
    folder, _ = spread_campaign
    for method in TINY.methods:
        whole = load_scores(TINY, folder, method, 3.0)
        assert sorted(k for k in whole if k != "process_device") == sorted(SCORE_FIELDS)
        assert len(whole["error"]) > 10 and np.isfinite(whole["density_cone_rel"]).any()
        for fields in (("error", "spread", "true_mag", "threshold"), ("density_cone_rel", "density_chief"),
                       ("measured",)):
            part = load_scores(TINY, folder, method, 3.0, fields=fields)
            assert sorted(part) == sorted([*fields, "process_device"])
            for k in fields:
                np.testing.assert_array_equal(part[k], whole[k])
            assert part["process_device"] == whole["process_device"] == "cpu"
    with pytest.raises(ValueError, match="unknown fields"):
        load_scores(TINY, folder, TINY.methods[0], 3.0, fields=("errors",))

def test_budget_figure_drawn_with_spread_and_skipped_without(spread_campaign, tmp_path, capsys):
    folder, _ = spread_campaign
    for fmt in ("png", "pdf"):
        assert (folder / f"fig_budget.{fmt}").stat().st_size > 10_000
    texts = []
    keep = figures.save_figure

    def capture(fig, path, **kw):
        texts.extend(t.get_text() for t in fig.findobj(figures.plt.Text))
        assert fig.get_size_inches()[0] == pytest.approx(7.2)  # journal width
        assert min(t.get_fontsize() for t in fig.findobj(figures.plt.Text) if t.get_text()) >= 7
        return keep(fig, path, **kw)

    figures.save_figure, saved = capture, figures.save_figure
    try:
        written = figures.figure_budget(TINY, folder, tmp_path / "budget", formats=("png",))
        sweep = figures.sweep_budget_figure([("1", TINY, folder), ("2", TINY, folder)], tmp_path / "sweep_budget",
                                            param_label="f-number", formats=("png",))
    finally:
        figures.save_figure = saved
    assert written == [tmp_path / "budget.png"] and sweep == [tmp_path / "sweep_budget.png"]
    assert any("threshold" in t and "px" in t for t in texts)
    assert "Cramér-Rao bound, median" in texts and "in-cone spread (px)" in texts
    assert "noise 3 %" in texts
    # Scores from before the spread was recorded: the table still loads, the figure is left out.
    folder = Path(shutil.copytree(folder, tmp_path / "old_campaign"))
    for method in TINY.methods:
        for noise in TINY.noise_percent:
            path = score_path(folder, 2, 0, noise, method)
            with np.load(path) as z:
                old = {k: z[k] for k in z.files if k != "spread"}
            with open(path, "wb") as f:
                np.savez(f, **old)
    rows = write_summary(TINY, folder)
    assert all(r["n_undistorted"] == 0 and r["p90_strong"] is None for r in rows)
    line = (folder / "results.csv").read_text().splitlines()[1]
    assert line.endswith(",0,,," * 4 + ",px")  # empty bins: empty fields; then the errors' unit
    assert figures.figure_budget(TINY, folder, tmp_path / "old", formats=("png",)) is None
    assert not (tmp_path / "old.png").exists()
