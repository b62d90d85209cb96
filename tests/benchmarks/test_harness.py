"""The harness end to end on a tiny campaign: resumable, deterministic, and the process/sweep commands."""

import json
from dataclasses import replace

import h5py
import numpy as np
import pytest
from synthbos.benchmarks.campaign import run_campaign
from synthbos.benchmarks.cli import main
from synthbos.benchmarks.integrate import density_floor_errors
from synthbos.benchmarks.spec import REGRESS
from synthbos.raytrace import read_pair, render_pair, write_pair

TINY_CONFIG = {
    "camera": {"pixels": [128, 128]},
    "target": {"dots_per_32px": 12.0},
    "volume": {"source": "slice", "distance_from_target_mm": 250.0, "size_mm": [32.0, 32.0, 10.0]},
    "rays": {"per_dot": 20},
}
TINY = replace(REGRESS, name="tiny", snapshots=(2,), noise_percent=(0.0, 3.0), config=TINY_CONFIG)


def test_campaign_is_resumable_and_deterministic(tmp_path, capsys):
    rows = run_campaign(TINY, tmp_path / "c", device="cpu", workers=1, progress=False, figures=False)
    assert {r["method"] for r in rows} == {"correlation", "tracking", "tracking-cc"}
    # methods x noise levels x (splits x displacement/gradient + 4 density quantities)
    assert len(rows) == 3 * 2 * (3 * 2 + 4)
    assert all(r["n"] > 0 for r in rows if r["split"] == "all")
    dens = [r for r in rows if r["quantity"] == "density_cone_rel"]
    assert len(dens) == 6 and all(0 < r["rms"] < 0.2 for r in dens)
    scores = sorted((tmp_path / "c" / "scores").iterdir())
    assert len(scores) == 3 * 2
    kept = [*scores, *(tmp_path / "c" / "floors").iterdir()]
    assert [p.name for p in kept[len(scores):]] == ["s2_p00.npz"]  # the pair's density floor, kept
    # results.csv names the unit of each row's errors, in a last column
    lines = (tmp_path / "c" / "results.csv").read_text().splitlines()
    header = lines[0].split(",")
    assert header[-1] == "error_units" and len(lines) == len(rows) + 1
    units = {(f := dict(zip(header, line.split(","), strict=True)))["quantity"]: f["error_units"] for line in lines[1:]}
    assert units == {"displacement": "px", "gradient": "px/px", "density_cone": "kg/m^3", "density_chief": "kg/m^3",
                     "density_cone_rel": "1", "density_chief_rel": "1"}
    # floor.csv: the density floor, the pair's exact displacements integrated and scored alike
    floor = json.loads((tmp_path / "c" / "floor.json").read_text())
    assert [(r["method"], r["quantity"]) for r in floor] == [("exact", q) for q in (
        "density_cone", "density_cone_rel", "density_chief", "density_chief_rel")]
    exact = density_floor_errors(tmp_path / "c" / "pairs" / "s2_p00.h5")
    by = {r["quantity"]: r for r in floor}
    assert by["density_cone_rel"]["rms"] == pytest.approx(np.sqrt(np.mean(exact["density_cone_rel"] ** 2)), rel=1e-12)
    assert 0 < by["density_cone_rel"]["rms"] < 0.2
    # A re-run skips finished work: nothing is rewritten (the floor neither), and it says so.
    stamps = {p: p.stat().st_mtime_ns for p in kept}
    capsys.readouterr()
    again = run_campaign(TINY, tmp_path / "c", device="cpu", workers=1, progress=True, figures=False)
    assert {p: p.stat().st_mtime_ns for p in kept} == stamps
    assert again == rows
    assert (f"resumed {tmp_path / 'c'}: 7 of 7 items already done (1 of 1 pairs rendered, 6 of 6 scores made), "
            "0 to run") in capsys.readouterr().out
    # An interrupted item (its file missing) is redone, with the same numbers.
    scores[0].unlink()
    third = run_campaign(TINY, tmp_path / "c", device="cpu", workers=1, progress=True, figures=False)
    assert "6 of 7 items already done (1 of 1 pairs rendered, 5 of 6 scores made), 1 to run" in capsys.readouterr().out
    assert third == rows
    # A different campaign in the same folder is refused.
    with pytest.raises(ValueError, match="different campaign"):
        run_campaign(replace(TINY, seed=1), tmp_path / "c", device="cpu", workers=1, progress=False)
    # The same campaign in a fresh folder gives the same table.
    fresh = run_campaign(TINY, tmp_path / "d", device="cpu", workers=1, progress=False, figures=False)
    assert fresh == rows
    assert not list((tmp_path / "c").rglob("*.tmp"))


def test_noise_makes_every_method_worse(tmp_path):
    rows = run_campaign(TINY, tmp_path / "c", device="cpu", workers=1, progress=False, figures=False)
    p50 = {(r["method"], r["noise_percent"]): r["p50"] for r in rows
           if r["split"] == "all" and r["quantity"] == "displacement"}
    for method in ("correlation", "tracking", "tracking-cc"):
        assert p50[(method, 3.0)] > p50[(method, 0.0)]


@pytest.fixture(scope="module")
def pair_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("pair") / "pair.h5"
    write_pair(path, render_pair(TINY_CONFIG, device="cpu"))
    return path


@pytest.mark.parametrize("method", ["correlation", "tracking", "tracking-cc"])
def test_process_pair_file(tmp_path, pair_file, method):
    out = tmp_path / "r.h5"
    assert main(["process", str(pair_file), "--method", method, "-o", str(out)]) == 0
    pair = read_pair(pair_file)
    with h5py.File(out) as f:
        assert f.attrs["method"] == method
        json.loads(f.attrs["settings"])
        if method == "correlation":
            assert f["u"].shape == f["x"].shape == f["flags"].shape == (8, 8)
            assert np.isfinite(f["u"][()]).all()
        else:
            u = np.stack([f["dots/u"][()], f["dots/v"][()]], axis=1)
            assert f["dots/status"].shape == (pair.n_dots,)
            ok = pair.valid & np.isfinite(u).all(axis=1)
            assert ok.mean() > 0.95
            err = np.hypot(*(u[ok] - pair.displacement_px[ok]).T)
            assert np.median(err) < 0.1


def test_process_camera_images_with_dots_csv(tmp_path, pair_file):
    import tifffile

    pair = read_pair(pair_file)
    scale = 60000 / pair.gradient.max()
    tifffile.imwrite(tmp_path / "a.tif", (pair.reference * scale).astype(np.uint16))
    tifffile.imwrite(tmp_path / "b.tif", (pair.gradient * scale).astype(np.uint16))
    dots = tmp_path / "dots.csv"
    dots.write_text("x,y\n" + "\n".join(f"{x:.4f},{y:.4f}" for x, y in pair.reference_px))
    out = tmp_path / "r.h5"
    args = ["process", "--reference", str(tmp_path / "a.tif"), "--gradient", str(tmp_path / "b.tif"),
            "--method", "tracking-cc", "--dots", str(dots), "-o", str(out)]
    assert main(args) == 0
    with h5py.File(out) as f:
        assert f["dots/x"].shape == (pair.n_dots,)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--reference", "nope.tif", "--gradient", "nope.tif"], "does not exist"),
        (["--reference", "a.tif"], "both --reference and --gradient"),
        (["--reference", "a.tif", "--gradient", "small.tif"], "shape"),
        (["--reference", "a.tif", "--gradient", "a.tif", "--dots", "bad.csv"], "header line"),
    ],
)
def test_process_bad_input_exits_2_without_output(tmp_path, capsys, monkeypatch, args, message):
    import tifffile

    monkeypatch.chdir(tmp_path)
    rng = np.random.default_rng(0)
    tifffile.imwrite("a.tif", (rng.random((64, 64)) * 1000).astype(np.uint16))
    tifffile.imwrite("small.tif", (rng.random((32, 64)) * 1000).astype(np.uint16))
    (tmp_path / "bad.csv").write_text("col,row\n1,2\n")
    assert main(["process", *args, "--method", "tracking", "-o", "out.h5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not (tmp_path / "out.h5").exists()


def test_sweep_writes_table_and_figure(tmp_path, capsys):
    cfg = tmp_path / "base.toml"
    cfg.write_text('[camera]\npixels = [96, 96]\n[rays]\nper_dot = 10\n[target]\ndots_per_32px = 10.0\n')
    out = tmp_path / "sweep"
    assert main(["sweep", str(cfg), "--param", "noise=0,4", "--out", str(out), "--workers", "1", "-q",
                 "--device", "cpu"]) == 0
    if not (out / "sweep_budget.png").exists():  # pairs without the ray covariance: said, not drawn
        assert "note: sweep_budget.png not drawn" in capsys.readouterr().out
    rows = json.loads((out / "sweep.json").read_text())
    assert {r["param_value"] for r in rows} == {0.0, 4.0}
    table = (out / "sweep.csv").read_text()  # a missing value (no second parameter, an empty bin) is an empty field
    assert "None" not in table and "null" not in table
    header, first = table.splitlines()[:2]
    fields = dict(zip(header.split(","), first.split(","), strict=True))
    assert (fields["param2"], fields["param2_value"], fields["error_units"]) == ("", "", "px")
    assert (out / "sweep.png").stat().st_size > 10_000
    assert main(["sweep", str(cfg), "--param", "bogus=1,2", "--out", str(out), "-q"]) == 2
