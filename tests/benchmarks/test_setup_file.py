"""Density from a camera pair: the ``[setup]`` description (``--setup-file``), the set-up a result records,
``integrate``'s refusal when none is known, and dots at the image's edge."""

import h5py
import numpy as np
import pytest
import tifffile
from numpy.testing import assert_allclose
from synthbos.benchmarks.cli import main
from synthbos.benchmarks.integrate import check_belongs, geometry_from_pair
from synthbos.benchmarks.process import read_result
from synthbos.benchmarks.setup_file import geometry_from_setup
from synthbos.raytrace import read_pair, render_pair, write_pair

from synthbos import SynthbosError

BLOB = {"camera": {"pixels": [96, 96]}, "rays": {"per_dot": 20},
        "volume": {"source": "gaussian", "amplitude_kg_m3": 0.3, "sigma_mm": 1.5, "grid": [32, 32, 8]}}
# The set-up of BLOB (the default camera and volume), as a user writes it.
SETUP = {"z_d_mm": 250.0, "depth_mm": 10.0, "target_distance_mm": 1000.0, "pixel_pitch_um": 10.0,
         "focal_length_mm": 105.0, "ambient_density_kg_m3": 1.225}


def _toml(table, name="[setup]"):
    lines = [name] + [f"{k} = {v!r}" if not isinstance(v, str) else f'{k} = "{v}"' for k, v in table.items()]
    return "\n".join(lines) + "\n"


@pytest.fixture(scope="module")
def camera(tmp_path_factory):
    """A rendered pair, its images as camera TIFFs (no truth), and a correlation result of each."""
    folder = tmp_path_factory.mktemp("camera")
    pair = render_pair(BLOB, device="cpu")
    write_pair(folder / "pair.h5", pair)
    tifffile.imwrite(folder / "ref.tif", np.asarray(pair.reference, np.float32))
    tifffile.imwrite(folder / "grad.tif", np.asarray(pair.gradient, np.float32))
    images = ["--reference", str(folder / "ref.tif"), "--gradient", str(folder / "grad.tif")]
    (folder / "camera.toml").write_text(_toml(SETUP))
    assert main(["process", *images, "--method", "correlation", "-o", str(folder / "bare.h5")]) == 0
    assert main(["process", *images, "--method", "correlation", "--setup-file", str(folder / "camera.toml"),
                 "-o", str(folder / "camera.h5")]) == 0
    assert main(["process", str(folder / "pair.h5"), "--method", "correlation", "-o", str(folder / "pair_r.h5")]) == 0
    return folder


def _error_line(capsys):
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip() and not ln.startswith("Warp")]
    assert len(err) == 1 and err[0].startswith("synthbos: error: "), err
    return err[0]


def test_the_setup_is_the_render_configurations():
    pair = render_pair(dict(BLOB, rays={"per_dot": 4}), device="cpu")
    want, got = geometry_from_pair(pair), geometry_from_setup(SETUP, (96, 96))
    for name in ("magnification", "pixel_pitch_m", "z_d_m", "z_stop_m", "depth_m", "gladstone_dale_m3_per_kg",
                 "n0", "ambient_density_kg_m3"):
        assert_allclose(getattr(got, name), getattr(want, name), rtol=1e-12, err_msg=name)
    assert got.principal_point_px == want.principal_point_px and got.image_shape == (96, 96)
    # The three ways of giving the scale agree.
    m = want.magnification
    by_m = geometry_from_setup({**{k: v for k, v in SETUP.items() if k != "focal_length_mm"}, "magnification": m},
                               (96, 96))
    mm_per_px = 10e-3 / m
    by_scale = geometry_from_setup({**{k: v for k, v in SETUP.items() if k != "focal_length_mm"},
                                    "target_mm_per_px": mm_per_px}, (96, 96))
    assert_allclose([by_m.mm_per_px, by_scale.mm_per_px], want.mm_per_px, rtol=1e-12)


def test_integrate_uses_the_recorded_setup_or_refuses(camera, tmp_path, capsys):
    out = tmp_path / "d.h5"
    # Camera images processed without a set-up: refused in one line, nothing written.
    assert main(["integrate", str(camera / "bare.h5"), "-o", str(out)]) == 2
    assert "records no set-up" in _error_line(capsys) and not out.exists()
    # The same result with --setup-file, the result that recorded it, and --pair: one density map.
    maps = {}
    for name, args in (("file", [str(camera / "bare.h5"), "--setup-file", str(camera / "camera.toml")]),
                       ("recorded", [str(camera / "camera.h5")]),
                       ("pair", [str(camera / "bare.h5"), "--pair", str(camera / "pair.h5")]),
                       ("pair-recorded", [str(camera / "pair_r.h5")])):
        assert main(["integrate", *args, "-o", str(tmp_path / f"{name}.h5")]) == 0
        with h5py.File(tmp_path / f"{name}.h5") as f:
            maps[name] = f["density_kg_m3"][()]
            source = f.attrs["setup_source"]
        print(f"{name}: set-up from {source}")
        assert {"file": "set-up file", "recorded": "(set-up file", "pair": "pair file",
                "pair-recorded": "(pair file"}[name] in source
    for name in ("recorded", "pair", "pair-recorded"):
        assert_allclose(maps[name], maps["file"], rtol=1e-9, equal_nan=True, err_msg=name)
    assert np.nanmax(maps["file"]) > 1.225 + 0.02
    _, attrs = read_result(camera / "camera.h5")
    assert '"z_d_m": 0.25' in attrs["setup"]


BAD = [
    ({k: v for k, v in SETUP.items() if k != "depth_mm"}, "[setup] needs depth_mm"),
    ({**SETUP, "magnification": 0.1}, "exactly one of magnification, focal_length_mm, target_mm_per_px"),
    ({k: v for k, v in SETUP.items() if k != "focal_length_mm"}, "exactly one of"),
    ({**SETUP, "z_d_mm": 1000.0}, "setup.z_d_mm = 1000 must be less than setup.target_distance_mm = 1000"),
    ({**SETUP, "z_d_mm": 999.0, "depth_mm": 100.0}, "949 ... 1049 mm from the target) must lie between the target"),
    ({**SETUP, "z_d_mm": 10.0, "depth_mm": 100.0}, "-40 ... 60 mm from the target) must lie between the target"),
    ({**SETUP, "depth_mm": -1.0}, "setup.depth_mm must be > 0 and <= 100000, got -1.0"),
    ({**SETUP, "depth_mm": "ten"}, "setup.depth_mm must be a number"),
    ({**SETUP, "ambient_density_kg_m3": float("nan")}, "setup.ambient_density_kg_m3 must be finite"),
    ({**SETUP, "focal_length_mm": 2000.0}, "setup.focal_length_mm = 2000 must be less than"),
    ({**SETUP, "zd_mm": 1.0}, "unknown [setup] key(s) zd_mm"),
    ({**SETUP, "principal_point_px": [1.0]}, "setup.principal_point_px must be a list of 2 numbers"),
]


@pytest.mark.parametrize(("table", "expected"), BAD)
def test_a_bad_setup_is_refused_in_one_line(camera, tmp_path, capsys, table, expected):
    bad = tmp_path / "bad.toml"
    bad.write_text(_toml(table))
    out = tmp_path / "d.h5"
    assert main(["integrate", str(camera / "bare.h5"), "--setup-file", str(bad), "-o", str(out)]) == 2
    assert expected in _error_line(capsys) and not out.exists()
    assert main(["process", "--reference", str(camera / "ref.tif"), "--gradient", str(camera / "grad.tif"),
                 "--method", "correlation", "--setup-file", str(bad), "-o", str(out)]) == 2
    assert expected in _error_line(capsys) and not out.exists()


def test_setup_files_and_options_that_do_not_fit(camera, tmp_path, capsys):
    out = tmp_path / "d.h5"
    cases = [
        (["integrate", str(camera / "bare.h5"), "--setup-file", str(camera / "nothing.toml")], "does not exist"),
        (["integrate", str(camera / "bare.h5"), "--setup-file", str(camera / "camera.toml"), "--pair",
          str(camera / "pair.h5")], "give one of --pair, --config and --setup-file"),
        (["integrate", str(camera / "pair.h5"), "--setup-file", str(camera / "camera.toml")], "is a pair file"),
        (["process", str(camera / "pair.h5"), "--method", "correlation", "--setup-file", str(camera / "camera.toml")],
         "holds its own set-up"),
    ]
    (tmp_path / "empty.toml").write_text("[tracking]\ndiameter = 3.0\n")
    cases.append((["integrate", str(camera / "bare.h5"), "--setup-file", str(tmp_path / "empty.toml")],
                  "has no [setup] table"))
    (tmp_path / "odd.toml").write_text(_toml(SETUP) + "[camera]\npixels = [96, 96]\n")
    cases.append((["integrate", str(camera / "bare.h5"), "--setup-file", str(tmp_path / "odd.toml")],
                  "unknown table(s) camera"))
    for args, expected in cases:
        assert main([*args, "-o", str(out)]) == 2, args
        assert expected in _error_line(capsys), args
        assert not out.exists()


def test_a_setup_table_in_the_process_configuration_is_recorded(camera, tmp_path):
    cfg = tmp_path / "process.toml"
    cfg.write_text("[correlation]\nwindow_sizes = [32, 16]\n\n" + _toml(SETUP))
    assert main(["process", "--reference", str(camera / "ref.tif"), "--gradient", str(camera / "grad.tif"),
                 "--method", "correlation", "--config", str(cfg), "-o", str(tmp_path / "r.h5")]) == 0
    _, attrs = read_result(tmp_path / "r.h5")
    assert f'"source": "process configuration {cfg}"' in attrs["setup"]
    assert main(["integrate", str(tmp_path / "r.h5"), "-o", str(tmp_path / "d.h5")]) == 0


def test_dots_at_the_image_edge_integrate(camera, tmp_path, capsys):
    """Tracking fits dots up to about a radius past the edge (1.2 px on camera images, 511.6 px on a 512 px
    thick-lens pair): accepted; a point farther out, or another image size, is no dot of these images."""
    pair = read_pair(camera / "pair.h5")
    geometry = geometry_from_pair(pair)
    result, attrs = read_result(camera / "pair_r.h5")
    W = pair.reference.shape[1]
    for x, fits in ((W - 0.5 + 1.2, True), (-0.5 - 1.9, True), (W - 0.5 + 2.5, False)):
        result.xy[0, 0] = x
        if fits:
            check_belongs(attrs, result, geometry)
        else:
            with pytest.raises(SynthbosError, match="reach more than 2 px beyond the pair's 96 x 96 px image"):
                check_belongs(attrs, result, geometry)
    # A tracking table's dots set the reach: half the largest diameter.
    result.table["diameter"] = np.full(len(result.xy), 6.0)
    result.xy[0, 0] = W - 0.5 + 2.9
    check_belongs(attrs, result, geometry)
    with pytest.raises(SynthbosError, match="do not belong together"):
        check_belongs({**attrs, "image_shape": np.array([96, 128])}, result, geometry)
    # Through the command: a tracked result whose edge dots reach 1.2 px past the edge.
    assert main(["process", str(camera / "pair.h5"), "--method", "tracking-cc", "-o", str(tmp_path / "t.h5")]) == 0
    with h5py.File(tmp_path / "t.h5", "r+") as f:
        x, ok = f["dots/x"][()], f["dots/valid"][()].astype(bool)
        edge = np.flatnonzero(ok)[np.argmax(x[ok])]
        x[edge] = W - 0.5 + 1.2
        f["dots/x"][...] = x
    assert main(["integrate", str(tmp_path / "t.h5"), "--pair", str(camera / "pair.h5"),
                 "-o", str(tmp_path / "d.h5")]) == 0
    assert main(["integrate", str(tmp_path / "t.h5"), "-o", str(tmp_path / "d2.h5")]) == 0
    capsys.readouterr()
