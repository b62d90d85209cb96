"""The worked example of docs/own-images.md, run on a laboratory-like set-up drawn here.

A calibration grid photographed with the camera, a printed random-dot target known in mm (dark dots
on white, 16-bit LZW TIFFs), a model masked out of the picture: ``calibrate --grid``, then
``calibrate --mapping --target`` gives the tracking prior, ``process`` with a configuration file
tracks every visible dot, and ``show-result`` draws it. The commands are those of that page.
"""

import csv

import h5py
import imageio.v3 as iio
import numpy as np
import tifffile
from synthbos.benchmarks.cli import main
from synthbos.benchmarks.process import read_dots_csv
from synthbos.raytrace.dots import draw_dots

SHAPE = (160, 192)
SHIFT = np.array([1.2, -0.7])
MASKED_COLUMNS = 28


def to_px(mm):
    """The camera: target mm -> image px, 6 px/mm, a 3 degree rotation and quadratic distortion."""
    c, s = np.cos(np.radians(3.0)), np.sin(np.radians(3.0))
    x, y = mm[:, 0], mm[:, 1]
    return np.stack([96.3 + 6.0 * (c * x - s * y) + 0.010 * x**2,
                     80.6 + 6.0 * (s * x + c * y) - 0.008 * x * y + 0.006 * y**2], axis=1)


def _tiff(path, bright_dots, rng, noise=0.01):
    """Dark dots on white, as printed and photographed: 16-bit, LZW-compressed."""
    img = 0.9 - 0.7 * bright_dots + noise * rng.standard_normal(SHAPE)
    tifffile.imwrite(path, np.clip(img * 60000, 0, 65535).astype(np.uint16), compression="lzw")


def _inside(px, margin):
    return (px[:, 0] > margin) & (px[:, 0] < SHAPE[1] - 1 - margin) & (px[:, 1] > margin) & (
        px[:, 1] < SHAPE[0] - 1 - margin)


def test_worked_example(tmp_path, capsys):
    rng = np.random.default_rng(2026)
    # The grid: 2 mm spacing, photographed once.
    g = np.arange(-20, 21) * 2.0
    gx, gy = np.meshgrid(g, g)
    grid_px = to_px(np.stack([gx.ravel(), gy.ravel()], axis=1))
    grid_px = grid_px[_inside(grid_px, -4)]
    _tiff(tmp_path / "grid.tif", draw_dots(SHAPE, grid_px, 3.0), rng)
    # The printed target: random dots known in mm, at least 0.8 mm apart.
    cand = rng.uniform(-17, 17, size=(4000, 2))
    keep = []
    for p in cand:
        if all(np.hypot(*(p - q)) >= 0.8 for q in keep):
            keep.append(p)
    target_mm = np.array(keep)
    with open(tmp_path / "target.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["x_mm", "y_mm"])
        w.writerows(target_mm.tolist())
    true_px = to_px(target_mm)
    _tiff(tmp_path / "ref.tif", draw_dots(SHAPE, true_px, 3.0), rng)
    _tiff(tmp_path / "grad.tif", draw_dots(SHAPE, true_px + SHIFT, 3.0), rng)
    # The mask: white where the pattern is seen, black over the model (the left columns).
    mask = np.full(SHAPE, 255, dtype=np.uint8)
    mask[:, :MASKED_COLUMNS] = 0
    iio.imwrite(tmp_path / "mask.png", mask)
    (tmp_path / "process.toml").write_text(
        '[correlation]\nwindow_sizes = [64, 32, 16]\noverlaps = 0.5\n\n'
        '[tracking]\ndiameter = 3.0\n\n'
        '[image]\nmask = "mask.png"\nmask_excludes = "dark"\ninvert = "auto"\n'
    )
    t = str(tmp_path)

    # 2. The prior: the mapping from the grid, then the target's dots through it.
    assert main(["calibrate", "--reference", f"{t}/grid.tif", "--grid", "2.0", "--invert",
                 "-o", f"{t}/grid_dots.csv", "--mapping-out", f"{t}/mapping.json"]) == 0
    assert main(["calibrate", "--mapping", f"{t}/mapping.json", "--target", f"{t}/target.csv",
                 "-o", f"{t}/dots.csv"]) == 0
    dots = read_dots_csv(tmp_path / "dots.csv")
    inside = _inside(true_px, 0)
    assert len(dots) >= inside.sum()
    nearest = np.min(np.hypot(*(dots[:, None, :] - true_px[None, inside, :]).transpose(2, 0, 1)), axis=0)
    print(f"calibrated prior: {inside.sum()} dots in view, largest error {nearest.max():.4f} px")
    assert nearest.max() < 0.05

    # 4. Process, with the configuration file (mask, automatic inversion of dark dots).
    assert main(["process", "--reference", f"{t}/ref.tif", "--gradient", f"{t}/grad.tif",
                 "--method", "tracking-cc", "--dots", f"{t}/dots.csv", "--settings", f"{t}/process.toml",
                 "-o", f"{t}/tracking.h5"]) == 0
    assert main(["process", "--reference", f"{t}/ref.tif", "--gradient", f"{t}/grad.tif",
                 "--method", "correlation", "--settings", f"{t}/process.toml", "-o", f"{t}/correlation.h5"]) == 0
    out = capsys.readouterr().out
    assert "inverted" in out and "measured" in out and "masked" in out
    with h5py.File(tmp_path / "tracking.h5") as f:
        x, y = f["dots/x"][()], f["dots/y"][()]
        u, v, masked = f["dots/u"][()], f["dots/v"][()], f["dots/masked"][()]
    visible = ~masked & (x > MASKED_COLUMNS + 3) & (x < SHAPE[1] - 5) & (y > 4) & (y < SHAPE[0] - 5)
    good = visible & np.isfinite(u)
    err = np.hypot(u[good] - SHIFT[0], v[good] - SHIFT[1])
    print(f"tracking-cc: {good.sum()} of {visible.sum()} visible dots measured, RMS error "
          f"{np.sqrt(np.mean(err**2)):.4f} px; {int(masked.sum())} masked")
    assert good.sum() >= 0.97 * visible.sum()
    assert np.sqrt(np.mean(err**2)) < 0.03
    assert masked.any() and np.isnan(u[masked]).all()
    xm = x[masked]  # not found (inside the excluded area) or touching its edge
    assert (np.isnan(xm) | (xm < MASKED_COLUMNS + 3)).all()

    # 5. Look at it.
    assert main(["show-result", f"{t}/correlation.h5", "-o", f"{t}/correlation.png"]) == 0
    assert (tmp_path / "correlation.png").stat().st_size > 0 and not (tmp_path / "correlation.pdf").exists()
