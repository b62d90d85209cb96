"""The density figure: writes a sensible PNG of the five embedded snapshots."""

import numpy as np
from synthbos.benchmarks.show_density import main, plot_snapshots


def test_plot_snapshots_writes_png(tmp_path):
    out = tmp_path / "density.png"
    stats = plot_snapshots(out, snapshots_file=None)
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(data) > 100_000, f"PNG only {len(data)} bytes"
    import matplotlib.image as mpimg

    img = mpimg.imread(out)
    assert img.shape[0] > 500 and img.shape[1] > 1500
    assert np.std(img[..., :3]) > 0.1  # not a blank canvas
    assert len(stats) == 5
    assert all(s["grad_flatness"] > 3.0 for s in stats), stats


def test_main_prints_table(tmp_path, capsys):
    out = tmp_path / "fig.png"
    assert main(["-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert out.is_file() and "flatness" in text and "wrote" in text


def test_show_density_command_names_its_file_and_draws_axes_with_units(tmp_path, capsys, monkeypatch):
    from figure_checks import assert_journal_figure
    from synthbos.benchmarks import show_density
    from synthbos.benchmarks.cli import main as cli_main

    figs = []
    save = show_density.save_figure
    monkeypatch.setattr(show_density, "save_figure", lambda fig, path, **kw: (figs.append(fig), save(fig, path, **kw)))
    out = tmp_path / "snapshots.jpg"
    assert cli_main(["show-density", "-o", str(out)]) == 0
    captured = capsys.readouterr()
    assert out.read_bytes()[:3] == b"\xff\xd8\xff" and sorted(p.name for p in tmp_path.iterdir()) == [out.name]
    assert f"wrote {out}" in captured.out and "show-density" in captured.err  # the progress bar
    (fig,) = figs
    assert_journal_figure(fig)
    labels = {a.get_xlabel() for a in fig.axes} | {a.get_ylabel() for a in fig.axes}
    assert {"x / L", "ρ / ⟨ρ⟩", "|∇ρ| (⟨ρ⟩ / L)"} <= labels
    assert cli_main(["show-density", "-o", str(tmp_path / "s.png"), "-q"]) == 0
    assert "show-density" not in capsys.readouterr().err
