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
