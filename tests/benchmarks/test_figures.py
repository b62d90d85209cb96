"""Figures a reviewer accepts: full-colour 300 dpi PNG beside a vector PDF, the threshold and counts
stated, sweep axes in words."""

from dataclasses import replace

import matplotlib.pyplot as plt
import numpy as np
import pytest
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
    png, pdf = stem.with_suffix(".png"), stem.with_suffix(".pdf")
    assert pdf.read_bytes()[:5] == b"%PDF-"
    with Image.open(png) as im:
        assert im.mode in ("RGB", "RGBA")  # no palette reduction
        assert round(im.info["dpi"][0]) == 300


@pytest.fixture
def captured(monkeypatch):
    """The figures a function saves, kept open for inspection (and still written)."""
    figs = []
    save = figures.save_figure

    def keep(fig, path, **kwargs):
        figs.append((fig, [t.get_text() for t in fig.findobj(plt.Text)]))
        return save(fig, path, **kwargs)

    monkeypatch.setattr(figures, "save_figure", keep)
    return figs


def test_campaign_figures_state_threshold_and_counts(tmp_path, captured):
    run_campaign(TINY, tmp_path, device="cpu", workers=1, progress=False)
    for stem in ("fig4", "fig5", "fig_density", "fig_budget"):
        _assert_png_and_pdf(tmp_path / stem)
    # fig4 is drawn once; fig5, fig_density and (the pairs record their ray covariance) fig_budget once for
    # each format (PNG, then PDF), alike
    (_, texts4), (_, texts5), (_, texts5_pdf), (_, texts_d), (_, texts_d_pdf), (_, texts_b), (_, texts_b_pdf) = captured
    assert texts5 == texts5_pdf and texts_d == texts_d_pdf and texts_b == texts_b_pdf
    assert any("ray-traced" in t for t in texts4)
    assert any("over the ray cone" in t for t in texts4)
    assert any("cone" in t and "chief" in t for t in texts_d)
    assert any(t.startswith("noise 0% (n = ") for t in texts_d)
    assert any("own scale" in t for t in texts4)
    title5 = next(t for t in texts5 if t.startswith("Error CDFs"))
    assert "Threshold" in title5 and " px" in title5
    assert sum(t.startswith("n = ") for t in texts5) == 4 * len(TINY.noise_percent) * len(TINY.methods)
    assert all(METHODS[name].label in texts5 for name in TINY.methods)


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
