"""``--setup NAME`` on the command line: render, paper and sweep start from a named set-up; an unknown name is
one line, exit status 2, nothing written."""

from pathlib import Path

import pytest
from synthbos.benchmarks import cli, sweep
from synthbos.benchmarks.cli import main, paper_spec
from synthbos.benchmarks.spec import QUICK
from synthbos.raytrace import load_config, read_pair, setup_tables

TINY = '[camera]\npixels = [48, 48]\n[rays]\nper_dot = 20\n[target]\ndots_per_32px = 8.0\n'


def _one_error_line(capsys, argv):
    rc = main([str(a) for a in argv])
    captured = capsys.readouterr()
    lines = [ln for ln in captured.err.splitlines() if ln.strip()]
    assert rc == 2, captured.err
    assert lines == ["synthbos: error: unknown set-up 'nope'; named set-ups: default, narrow"]
    assert "device" not in captured.out  # refused before the device is even reported


def test_render_starts_from_the_named_setup_and_the_file_changes_it(tmp_path):
    cfg_file = tmp_path / "tiny.toml"
    cfg_file.write_text(TINY)
    out = tmp_path / "p.h5"
    assert main(["render", str(cfg_file), "--setup", "narrow", "-o", str(out), "--device", "cpu", "-q"]) == 0
    pair = read_pair(out)
    expected = load_config(cfg_file, setup="narrow")
    assert expected["camera"]["pixels"] == [48, 48] and expected["camera"]["f_number"] == 32.0
    assert pair.reference.shape == (48, 48)
    assert "f_number = 32.0" in pair.attrs["config"]
    assert "density_scale_kg_m3 = 1.225" in pair.attrs["config"]


@pytest.mark.parametrize("argv", [
    ["render", "--setup", "nope", "-o", "{tmp}/p.h5"],
    ["paper", "--quick", "--setup", "nope", "--out", "{tmp}/campaign"],
    ["sweep", "--setup", "nope", "--param", "f_number=8,16", "--out", "{tmp}/sweep"],
])
def test_unknown_setup_is_one_line_and_writes_nothing(tmp_path, capsys, argv):
    _one_error_line(capsys, [a.format(tmp=tmp_path) for a in argv])
    assert list(Path(tmp_path).iterdir()) == []


def test_paper_spec_merges_the_setup_and_names_the_campaign():
    assert paper_spec() == QUICK
    spec = paper_spec(setup="narrow", methods="correlation,tracking-cc")
    assert spec.name == "quick-narrow"
    assert spec.methods == ("correlation", "tracking-cc")
    assert spec.config == {**QUICK.config, **setup_tables("narrow")}
    assert spec.pair_config(2, 0)["target"]["seed"] == QUICK.pair_config(2, 0)["target"]["seed"]  # same dots


def test_paper_and_sweep_pass_the_setup_on(tmp_path, monkeypatch):
    """The commands hand the set-up's configuration to the campaign and the sweep (stand-ins record it)."""
    seen = {}

    def fake_campaign(spec, out, **kwargs):
        seen["campaign"] = (spec, Path(out))
        return []

    def fake_sweep(base, params, out, **kwargs):
        seen["sweep"] = (base, params)
        return []

    monkeypatch.setattr(cli, "run_campaign", fake_campaign)
    monkeypatch.setattr(sweep, "run_sweep", fake_sweep)
    monkeypatch.chdir(tmp_path)
    assert main(["paper", "--quick", "--setup", "narrow", "--device", "cpu", "-q"]) == 0
    spec, out = seen["campaign"]
    assert spec.name == "quick-narrow" and out == Path("runs/paper-quick-narrow")
    assert spec.config["camera"]["f_number"] == 32.0
    cfg_file = tmp_path / "tiny.toml"
    cfg_file.write_text(TINY)
    assert main(["sweep", str(cfg_file), "--setup", "narrow", "--param", "f_number=16,32", "--out", "s",
                 "--device", "cpu", "-q"]) == 0
    base, params = seen["sweep"]
    assert base == {"camera": {"f_number": 32.0, "pixels": [48, 48]}, "rays": {"per_dot": 20},
                    "target": {"dots_per_32px": 8.0}}
    assert params == [("camera.f_number", [16.0, 32.0])]
