"""Figures a reviewer accepts: full-colour 300 dpi PNG beside a vector PDF, the threshold and counts
stated, sweep axes in words."""

from dataclasses import replace
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pytest
from figure_checks import assert_journal_figure
from PIL import Image
from synthbos.benchmarks import figures
from synthbos.benchmarks.campaign import run_campaign
from synthbos.benchmarks.registry import METHODS
from synthbos.benchmarks.spec import REGRESS
from synthbos.benchmarks.sweep import parameter_label

TINY = replace(
    REGRESS,
    name="tiny-fig",
    snapshots=(2,),
    noise_percent=(0.0, 3.0),
    config={"camera": {"pixels": [96, 96]}, "target": {"dots_per_32px": 12.0}, "rays": {"per_dot": 10}},
)


def _assert_png_and_pdf(stem):
    png, pdf, svg = stem.with_suffix(".png"), stem.with_suffix(".pdf"), stem.with_suffix(".svg")
    assert pdf.read_bytes()[:5] == b"%PDF-"
    assert b"<svg" in svg.read_bytes()[:2000]
    with Image.open(png) as im:
        assert im.mode in ("RGB", "RGBA")  # no palette reduction
        assert round(im.info["dpi"][0]) == 300


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    """The TINY campaign, run once, and the figures it saved (stem, figure, its texts), kept open."""
    folder = tmp_path_factory.mktemp("tiny-fig")
    figs = []
    save = figures.save_figure

    def keep(fig, path, **kwargs):
        figs.append((Path(path).with_suffix("").name, fig, [t.get_text() for t in fig.findobj(plt.Text)]))
        return save(fig, path, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(figures, "save_figure", keep)
        run_campaign(TINY, folder, device="cpu", workers=1, progress=False)
    return folder, figs


def test_campaign_figures_state_threshold_and_counts(campaign):
    folder, captured = campaign
    for stem in ("fig4", "fig5", "fig_density", "fig_budget"):
        _assert_png_and_pdf(folder / stem)
    texts = {}
    for stem, _, t in captured:
        texts.setdefault(stem, []).append(t)
    # on one worker every figure, fig_budget too (the pairs record their ray covariance), is drawn once and
    # saved in every format (PNG, PDF, SVG); with a worker for each format, once per format
    # (campaign._figure_jobs; test_saved_figures_are_the_same_bytes_every_time: the same files either way)
    for stem in ("fig4", "fig5", "fig_density", "fig_budget"):
        assert len(texts[stem]) == 1, stem
    texts4, texts5, texts_d = texts["fig4"][0], texts["fig5"][0], texts["fig_density"][0]
    assert any("ray-traced" in t for t in texts4)
    assert any("over the ray cone" in t for t in texts4)
    assert any("cone" in t and "chief" in t for t in texts_d)
    assert any(t.startswith("noise 0% (n = ") for t in texts_d)
    assert any("own scale" in t for t in texts4)
    title5 = next(t for t in texts5 if t.startswith("Error CDFs"))
    assert "Threshold" in title5 and " px" in title5
    assert sum(t.startswith("n = ") for t in texts5) == 4 * len(TINY.noise_percent) * len(TINY.methods)
    assert all(METHODS[name].label in texts5 for name in TINY.methods)


def _drawn(monkeypatch, draw):
    """The figures ``draw()`` saves, each checked as saved."""
    figs = []
    save = figures.save_figure

    def keep(fig, path, **kwargs):
        written = save(fig, path, **kwargs)
        figs.append((fig, written))
        return written

    monkeypatch.setattr(figures, "save_figure", keep)
    draw()
    monkeypatch.setattr(figures, "save_figure", save)
    return figs


def _clims(axes):
    return {tuple(np.round(im.get_clim(), 12)) for ax in axes for im in ax.get_images()}


def test_campaign_figures_fit_a_journal(campaign, tmp_path, monkeypatch):
    folder, _ = campaign
    for stem, draw in figures.CAMPAIGN_FIGURES.items():
        figs = _drawn(monkeypatch, lambda draw=draw, stem=stem: draw(TINY, folder, tmp_path / stem))
        assert len(figs) == 1
        fig, written = figs[0]
        assert sorted(p.suffix for p in written) == [".pdf", ".png", ".svg"]
        assert all(p.stat().st_size > 5_000 for p in written)
        assert_journal_figure(fig)
        grid = np.array(fig.axes[: len(fig.axes) - sum(getattr(a, "_colorbar", None) is not None for a in fig.axes)])
        if stem == "fig5":  # the CDFs: one probability axis for every row
            assert len({ax.get_ylim() for ax in grid}) == 1
        if stem == "fig_density":  # one density scale, one error scale, one CDF axis in every row
            rows = grid.reshape(len(TINY.methods), 5)
            assert len(_clims(rows[:, :2].ravel())) == 1 and len(_clims(rows[:, 2])) == 1
            assert len({(ax.get_xlim(), ax.get_ylim()) for ax in rows[:, 3:].ravel()}) == 1
            styles = {ln.get_linestyle() for ln in rows[0, 3].get_lines()}
            assert len(styles) == len(TINY.noise_percent)  # noise levels told apart by line style
        if stem == "fig4":  # the rows of a column share its scale
            rows = grid.reshape(len(TINY.snapshots), 5)
            assert all(len(_clims(rows[:, c])) == 1 for c in range(5))


def test_sweep_figure_fits_a_journal_and_keeps_the_yield_axis_readable(tmp_path, monkeypatch):
    rows = []
    for method in ("correlation", "tracking"):
        for noise in (0.0, 3.0):
            for k, value in enumerate((11.0, 16.0, 22.0)):
                base = {"method": method, "noise_percent": noise, "param_value": value, "param2_value": None,
                        "split": "all"}
                rows.append({**base, "quantity": "displacement", "p50": 0.01 * (k + 1), "p90": 0.03 * (k + 1),
                             "yield": 1.0 - 0.0004 * k})
                rows.append({**base, "quantity": "density_cone_rel", "rms": 0.002 * (k + 1), "yield": 1.0})
    figs = _drawn(monkeypatch, lambda: figures.sweep_figure(rows, tmp_path / "sweep.png", param="camera.f_number",
                                                            param_label="f-number"))
    (fig, written), = figs
    assert sorted(p.name for p in written) == ["sweep.pdf", "sweep.png", "sweep.svg"]
    assert_journal_figure(fig)
    yield_axes = [ax for ax in fig.axes if ax.get_ylabel() == "fraction measured"]
    assert len(yield_axes) == 2
    for ax in yield_axes:
        lo, hi = ax.get_ylim()
        assert lo == pytest.approx(0.95) and 1.0 < hi <= 1.01  # not stretched over 0.9992 to 1
    assert figures.yield_limits([np.array([0.2, 0.9])]) == pytest.approx((0.15, 1.0425))
    assert figures.yield_limits([np.array([0.01, 1.0])]) == pytest.approx((0.0, 1.05))


def test_log_limits_fit_the_data():
    lo, hi = figures._log_limits([np.array([1e-3, 2e-3, 0.05, np.nan, 0.0])], low_quantile=0.0, margin=1.25)
    assert lo == pytest.approx(1e-3 / 1.25) and hi == pytest.approx(0.05 * 1.25)


def test_sweep_parameters_are_named_in_words_with_units():
    assert parameter_label("camera.f_number") == "f-number"
    assert parameter_label("target.dots_per_32px") == "dot density (dots per 32 × 32 px)"
    assert parameter_label("volume.density_scale_kg_m3") == "volume density scale (kg/m³)"
    assert parameter_label("noise").endswith("(% of the dot peak)")


def _busy_figure():
    """Constrained layout, log axes with unlabelled minor ticks and a minor grid, shared axes, a colour
    bar, a legend outside: what save_figure's shortcuts (one layout, minor ticks as lines, cached ticks)
    must draw as matplotlib's own savefig does."""
    rng = np.random.default_rng(3)
    fig, axes = plt.subplots(2, 3, figsize=(10, 5), layout="constrained", sharey="row")
    for k, ax in enumerate(axes.flat):
        e = np.sort(rng.lognormal(-6, 1.5, 500))
        ax.step(e, np.linspace(0, 1, len(e)), where="post", label=f"curve {k}")
        ax.set_xscale("log")
        ax.set_xlim(10.0 ** (-5 + k % 3), 10.0 ** (-2 + k % 2))
        ax.grid(True, which="both" if k % 2 else "major", alpha=0.3)
        ax.set_xlabel("error (px)")
    figures._log_axis(axes[0, 0].xaxis, 1e-5, 1e-3)  # a narrow axis: labelled 1, 2, 5 ... ticks
    axes[0, 0].set_xlim(1e-5, 1e-3)
    im = axes[1, 2].inset_axes((0.1, 0.5, 0.4, 0.4)).imshow(rng.random((8, 8)))
    figures._colorbar(fig, im, axes[1, 2], label="ρ (kg/m³)")
    fig.legend(*axes[0, 0].get_legend_handles_labels(), loc="outside lower center")
    fig.suptitle("busy")
    return fig


def test_save_figure_draws_what_savefig_draws(tmp_path):
    fig = _busy_figure()
    fig.savefig(tmp_path / "plain.png", dpi=300)
    plt.close(fig)
    figures.save_figure(_busy_figure(), tmp_path / "fast")
    _assert_png_and_pdf(tmp_path / "fast")
    with Image.open(tmp_path / "plain.png") as a, Image.open(tmp_path / "fast.png") as b:
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_saved_figures_are_the_same_bytes_every_time(tmp_path):
    """No date and no random ids: the same figure gives the same PNG, PDF and SVG files, whether its formats
    are saved together or each by a call of its own (as a campaign on many workers does)."""
    with figures.journal_style():
        figures.save_figure(_busy_figure(), tmp_path / "a")
        for fmt in figures.FORMATS:
            figures.save_figure(_busy_figure(), tmp_path / "b", formats=(fmt,))
    for fmt in figures.FORMATS:
        assert (tmp_path / f"a.{fmt}").read_bytes() == (tmp_path / f"b.{fmt}").read_bytes(), fmt


def test_docs_figures_are_made_by_one_script(campaign, tmp_path, capsys):
    """docs/make_figures.py draws the docs' campaign figures from a campaign folder and says what it wrote."""
    import importlib.util

    script = Path(__file__).resolve().parents[2] / "docs" / "make_figures.py"
    spec = importlib.util.spec_from_file_location("make_figures", script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    folder, _ = campaign
    assert module.main(["--campaign", str(folder), "-o", str(tmp_path), "--work", str(tmp_path / "work"),
                        "--width", "720"]) == 0
    printed = capsys.readouterr().out
    for stem in ("fig4", "fig5", "fig_density", "fig_budget"):
        path = tmp_path / f"quick_{stem}.png"
        with Image.open(path) as im:
            assert im.size[0] == 720
        assert f"wrote {path}: 720 x " in printed
    assert f"left {tmp_path / 'fig5_default.png'} as it is (no --fig5)" in printed
