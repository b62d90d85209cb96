"""The processing device of campaigns and of ``process``, and the GPU campaign's pipeline scheduling (on the CPU)."""

import json
import shutil
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest
from synthbos.benchmarks.campaign import resolve_process_device, run_campaign
from synthbos.benchmarks.cli import main
from synthbos.benchmarks.spec import REGRESS
from synthbos.raytrace import render_pair, write_pair

SMALL_CONFIG = {
    "camera": {"pixels": [96, 96]},
    "target": {"dots_per_32px": 12.0},
    "rays": {"per_dot": 10},
}
# Two pairs, two noise levels, every default method: 12 score items.
SMALL = replace(REGRESS, name="small", snapshots=(1, 3), noise_percent=(0.0, 3.0), config=SMALL_CONFIG)


def _pair_datasets(path):
    with h5py.File(path) as f:
        data = {}
        f.visititems(lambda name, obj: data.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
        attrs = {k: v for k, v in f.attrs.items() if k != "render_seconds"}
    return data, attrs


def assert_same_files(a, b):
    """Two campaign folders hold the same files with the same contents (pairs: all but the render time)."""
    files_a = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file() and p.name != ".lock")
    files_b = sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file() and p.name != ".lock")
    assert files_a == files_b
    assert sum(p.parts[0] == "scores" for p in files_a) == 12
    assert sum(p.parts[0] == "floors" for p in files_a) == 2  # each pair's density floor
    for rel in files_a:
        if rel.suffix == ".h5":
            (da, attrs_a), (db, attrs_b) = _pair_datasets(a / rel), _pair_datasets(b / rel)
            assert str(attrs_a) == str(attrs_b) and sorted(da) == sorted(db)
            for k in da:  # text datasets (dimension-scale labels) read as objects: compare their values
                same = (da[k].tolist() == db[k].tolist() if np.asarray(da[k]).dtype == object
                        else da[k].tobytes() == db[k].tobytes())
                assert same, (rel, k)
        elif rel.suffix == ".npz":  # np.savez stamps zip member times: compare the arrays
            with np.load(a / rel) as za, np.load(b / rel) as zb:
                assert sorted(za.files) == sorted(zb.files)
                for k in za.files:
                    assert za[k].dtype == zb[k].dtype and za[k].tobytes() == zb[k].tobytes(), (rel, k)
        else:
            assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    """The campaign as the CPU runs it: renders, then score items (one worker: in this process)."""
    folder = tmp_path_factory.mktemp("plain") / "c"
    rows = run_campaign(SMALL, folder, device="cpu", workers=1, progress=False, figures=False, pipeline=False)
    return folder, rows


def test_pipeline_gives_the_plain_campaign_byte_for_byte_and_resumes(plain, tmp_path):
    folder, rows = plain
    # device work here and scoring in one worker process, as a GPU campaign runs (here on the CPU)
    piped = run_campaign(SMALL, tmp_path / "p", device="cpu", workers=2, progress=False, figures=False,
                         pipeline=True)
    assert piped == rows
    assert {r["process_device"] for r in rows} == {"cpu"}
    assert_same_files(folder, tmp_path / "p")
    # an interrupted pipeline run: one pair and some scores missing; the rest is kept, the result the same
    resumed = tmp_path / "r"
    shutil.copytree(folder, resumed)
    for p in [*sorted((resumed / "scores").glob("*.npz"))[::3], next((resumed / "pairs").glob("*.h5"))]:
        p.unlink()
    kept = {p: p.stat().st_mtime_ns for p in (resumed / "scores").glob("*.npz")}
    again = run_campaign(SMALL, resumed, device="cpu", workers=1, progress=False, figures=False, pipeline=True)
    assert again == rows
    assert {p: p.stat().st_mtime_ns for p in kept} == kept
    assert_same_files(folder, resumed)


def test_score_files_record_the_processing_device(plain):
    folder, _ = plain
    for path in (folder / "scores").glob("*.npz"):
        with np.load(path) as z:
            assert str(z["process_device"]) == "cpu"
    assert json.loads((folder / "results.json").read_text())[0]["process_device"] == "cpu"
    assert "process_device" in (folder / "results.csv").read_text().splitlines()[0].split(",")


def test_processing_device_defaults_to_the_render_device():
    assert resolve_process_device(None, None) == "cpu"
    assert resolve_process_device("cuda:0", None) == "cuda:0"
    assert resolve_process_device("cuda:0", "cpu") == "cpu"


def _one_line_error(capsys, argv, expected):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("synthbos: error:") and expected in err[0], err


@pytest.fixture(scope="module")
def pair_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("pair") / "pair.h5"
    write_pair(path, render_pair({**SMALL_CONFIG, "camera": {"pixels": [128, 128]}}, device="cpu"))
    return path


def test_process_device_is_used_and_recorded(pair_file, tmp_path, capsys):
    out = tmp_path / "r.h5"
    assert main(["process", str(pair_file), "--method", "correlation", "--device", "cpu", "-o", str(out)]) == 0
    assert "device: cpu" in capsys.readouterr().out
    with h5py.File(out) as f:
        assert f.attrs["device"] == "cpu"
        assert json.loads(f.attrs["settings"])["device"] == "cpu"


@pytest.mark.parametrize("bad", ["gpu:0", "cuda:7"])
def test_bad_process_device_is_one_line_and_writes_nothing(pair_file, tmp_path, capsys, bad):
    import warp as wp

    if bad == "cuda:7" and wp.get_cuda_device_count() > 7:
        pytest.skip("this machine has a cuda:7")
    out = tmp_path / "r.h5"
    _one_line_error(capsys, ["process", str(pair_file), "--method", "tracking", "--device", bad, "-o", str(out)],
                    repr(bad))
    assert not out.exists()
    _one_line_error(capsys, ["paper", "--quick", "--device", "cpu", "--process-device", bad, "--out",
                             str(tmp_path / "paper"), "-q"], repr(bad))
    _one_line_error(capsys, ["sweep", "--param", "noise=0", "--device", bad, "--out", str(tmp_path / "sweep"),
                             "-q"], repr(bad))
    assert not (tmp_path / "paper").exists() and not (tmp_path / "sweep").exists()


def test_paper_and_sweep_pass_the_devices_on(plain, tmp_path, capsys, monkeypatch):
    """``--device`` renders and processes, ``--process-device`` overrides the processing device."""
    import synthbos.benchmarks.cli as cli
    import synthbos.benchmarks.sweep as sweep

    calls = []
    monkeypatch.setattr(cli, "run_campaign", lambda spec, out, **kw: calls.append(kw) or plain[1])
    monkeypatch.setattr(sweep, "run_sweep", lambda *a, **kw: calls.append(kw) or [])
    assert main(["paper", "--quick", "--device", "cpu", "--out", str(tmp_path / "a"), "-q"]) == 0
    assert main(["paper", "--quick", "--device", "cpu", "--process-device", "cpu", "--out", str(tmp_path / "b"),
                 "-q"]) == 0
    assert main(["sweep", "--param", "noise=0", "--device", "cpu", "--out", str(tmp_path / "c"), "-q"]) == 0
    assert [(c["device"], c["process_device"]) for c in calls] == [("cpu", "cpu")] * 3
    assert "device: cpu" in capsys.readouterr().out


def test_tracking_and_tracking_cc_share_one_track_pair(pair_file):
    """A pair's tracking items, one after the other, run ``track_pair`` once; the results are those of two runs."""
    from synthbos.benchmarks import registry
    from synthbos.benchmarks.items import measure_pair
    from synthbos.raytrace import read_pair

    pair = read_pair(pair_file)
    calls = []
    fn = registry._track_pair.fn
    registry.forget_shared_results()
    try:
        registry._track_pair.fn = lambda *a, **kw: calls.append(1) or fn(*a, **kw)
        shared = {m: measure_pair(pair, m, noise_percent=3.0, seeds=(5, 6), device="cpu")
                  for m in ("tracking", "tracking-cc")}
        assert len(calls) == 1
        alone = {}
        for m in ("tracking", "tracking-cc"):
            registry.forget_shared_results()
            alone[m] = measure_pair(pair, m, noise_percent=3.0, seeds=(5, 6), device="cpu")
        assert len(calls) == 3
        other_noise = measure_pair(pair, "tracking-cc", noise_percent=1.0, seeds=(5, 6), device="cpu")
        assert len(calls) == 4 and not np.array_equal(other_noise.uv, alone["tracking-cc"].uv, equal_nan=True)
    finally:
        registry._track_pair.fn = fn
        registry.forget_shared_results()
    for m in shared:
        assert shared[m].uv.tobytes() == alone[m].uv.tobytes()
        for k in shared[m].table:
            assert np.asarray(shared[m].table[k]).tobytes() == np.asarray(alone[m].table[k]).tobytes(), (m, k)
    assert not np.array_equal(shared["tracking"].uv, shared["tracking-cc"].uv, equal_nan=True)


def test_bench_stages_times_every_stage_on_the_cpu(capsys):
    from synthbos.benchmarks.bench_stages import format_table, time_stages

    run = time_stages("cpu", rays_per_dot=6, scale_to=10_000, repeats=1, base_config=SMALL_CONFIG)
    stages = run["stages"]
    expected = ["render", "pair file", "noise", "correlation", "tracking", "tracking-cc", "methods in turn",
                "score correlation", "score tracking", "score tracking-cc", "pair total"]
    assert list(stages) == expected and all(t > 0 for t in stages.values())
    # the render is scaled from 6 to 10,000 rays per dot; the measured time is kept (on a busy machine the
    # 2-ray render can time no faster than the 6-ray one: then the scaled time is the measured one)
    assert stages["render"] >= run["measured"]["render"] and run["render_scaled_to_rays_per_dot"] == 10_000
    assert stages["pair total"] > stages["render"] + 4 * stages["methods in turn"]
    table = format_table([run, run])
    assert "cpu/cpu" in table and "render scaled to 10000 rays/dot" in table


def test_bench_stages_times_batched_tracking():
    from synthbos.benchmarks.bench_stages import time_stages

    run = time_stages("cpu", rays_per_dot=6, scale_to=6, repeats=1, base_config=SMALL_CONFIG, methods=["tracking"],
                      batch=3)
    tb = run["tracking_batch"]
    assert tb["pairs"] == 3 and tb["dots"] == 3 * run["dots"]
    assert tb["dots_per_second"] == pytest.approx(tb["dots"] / tb["seconds"])
    assert run["stages"]["tracking, batched"] == pytest.approx(tb["seconds"] / 3)
    # the batch's first and last pairs are track_pair's results
    assert tb["status_equal"] and tb["max_difference_px"] < 1e-9
    # the warm-up and the timed call, from images on the device: the same bytes
    assert tb["calls"] == 2 and tb["calls_identical"]


def test_an_error_in_the_pipeline_stops_it_and_a_rerun_finishes(plain, tmp_path, monkeypatch):
    import synthbos.benchmarks.items as items

    folder, rows = plain
    out = tmp_path / "c"
    shutil.copytree(folder, out)
    for p in [*(out / "scores").glob("s1_*.npz"), out / "results.json", out / "results.csv"]:  # one pair's 6
        p.unlink()
    finish, done = items.finish_item, []

    def failing(*args, **kw):
        if len(done) == 2:
            raise RuntimeError("scoring failed")
        done.append(finish(*args, **kw))
        return done[-1]

    monkeypatch.setattr(items, "finish_item", failing)
    with pytest.raises(RuntimeError, match="scoring failed"):
        run_campaign(SMALL, out, device="cpu", workers=1, progress=False, figures=False, pipeline=True)
    assert len(list((out / "scores").glob("*.npz"))) == 6 + 2 and not list(out.rglob("*.tmp"))
    monkeypatch.setattr(items, "finish_item", finish)
    assert run_campaign(SMALL, out, device="cpu", workers=1, progress=False, figures=False, pipeline=True) == rows
    assert_same_files(folder, out)


def test_pipeline_scores_a_noise_levels_items_together():
    from synthbos.benchmarks.scheduling import same_image_runs

    scores = [(f"p{p}.h5", m, noise, (7 * p + int(noise), 1), f"{p}{noise}{m}.npz", {}, "cpu")
              for p in (1, 2) for noise in (0.0, 3.0) for m in ("correlation", "tracking", "tracking-cc")]
    runs = same_image_runs(scores)
    assert [len(r) for r in runs] == [3, 3, 3, 3] and [x for r in runs for x in r] == scores
    assert all(len({(a[0], a[2], a[3]) for a in r}) == 1 for r in runs)
    # a resumed campaign lists only the missing items: runs never join different images
    missing = scores[1:2] + scores[4:8]
    assert [[a[4] for a in r] for r in same_image_runs(missing)] == [
        ["10.0tracking.npz"], ["13.0tracking.npz", "13.0tracking-cc.npz"], ["20.0correlation.npz", "20.0tracking.npz"]]


def test_worker_device_moves_only_the_methods_with_host_work():
    from synthbos.benchmarks.scheduling import split_by_residency

    run = [("p.h5", m, 1.0, (1, 2), f"{m}.npz", {}, "cuda:0") for m in ("correlation", "tracking", "tracking-cc")]
    here, there = split_by_residency(run)
    assert [a[1] for a in here] == ["correlation"] and [a[1] for a in there] == ["tracking", "tracking-cc"]
    assert {a[-1] for a in here + there} == {"cuda:0"}
    here, there = split_by_residency(run, worker_device="cpu")
    assert here == run[:1] and there == [(*a[:-1], "cpu") for a in run[1:]]


@pytest.mark.parametrize(("given", "used"), [(None, "cpu"), ("cpu", "cpu"), ("cuda:0", "cuda:0")])
def test_pipeline_workers_process_on_the_cpu_unless_told(tmp_path, monkeypatch, given, used):
    """A GPU campaign's workers run tracking on their CPU cores by default (PIPELINE_WORKER_DEVICE)."""
    from synthbos.benchmarks import campaign

    seen = []

    def pipeline(renders, scores, *, worker_device, jobs, **kwargs):
        seen.append(worker_device)
        raise KeyboardInterrupt  # nothing to run: the test stops here

    monkeypatch.setattr(campaign, "run_pipeline", pipeline)
    with pytest.raises(KeyboardInterrupt):
        run_campaign(SMALL, tmp_path / "c", device="cpu", workers=2, progress=False, pipeline=True,
                     worker_device=given)
    assert seen == [used] and campaign.PIPELINE_WORKER_DEVICE == "cpu"


def test_bad_worker_device_is_one_line(tmp_path, capsys):
    assert main(["paper", "--quick", "--device", "cpu", "--worker-device", "gpu:3", "--out", str(tmp_path / "w")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "gpu:3" in err[0]
    assert not (tmp_path / "w").exists()


def test_pipeline_draws_first_pair_figures_early_and_the_rest_after_the_last_item(plain, tmp_path, monkeypatch):
    """fig4 reads only the snapshots' first pairs: the pipeline draws it as soon as they are rendered
    (before the last pair's items are scored); the tables and the other figures come after the last item
    (on one worker each figure drawn once for every format; with a worker for each format, a job each:
    ``campaign._figure_jobs``)."""
    from synthbos.benchmarks import figures

    seen = {}
    drawn = {}  # stem -> the formats of each call

    def recorder(stem):
        def draw(spec, folder, path, *, formats=None):
            seen[stem] = len(list((Path(folder) / "scores").glob("*.npz")))
            drawn.setdefault(stem, []).append(formats)
        return draw

    for stem in figures.CAMPAIGN_FIGURES:
        monkeypatch.setitem(figures.CAMPAIGN_FIGURES, stem, recorder(stem))
    timings = {}
    rows = run_campaign(SMALL, tmp_path / "f", device="cpu", workers=1, progress=False, figures=True,
                        pipeline=True, timings=timings)
    assert rows == plain[1]
    assert seen["fig4"] < 12 and seen["fig5"] == seen["fig_density"] == seen["fig_budget"] == 12
    assert drawn == {"fig4": [None], "fig5": [None], "fig_density": [None], "fig_budget": [None]}
    assert (tmp_path / "f" / "results.csv").read_bytes() == (plain[0] / "results.csv").read_bytes()
    assert set(timings) == {"render and process", "tables and figures, after the last item"}


def test_one_gpu_pipeline_starts_at_most_sixteen_host_processes(monkeypatch):
    """Without --workers a GPU's pipeline takes every core up to ``PIPELINE_MAX_WORKERS`` (more were slower on
    every larger host measured); a CPU campaign every core; Dask GPU workers a share of them, as capped."""
    from synthbos.benchmarks import scheduling

    monkeypatch.setattr(scheduling, "default_workers", lambda: 64)
    assert scheduling.PIPELINE_MAX_WORKERS == 16
    assert scheduling.pipeline_workers() == 16
    assert scheduling.pipeline_workers(4) == 16 and scheduling.pipeline_workers(8) == 8
    monkeypatch.setattr(scheduling, "default_workers", lambda: 2)
    assert scheduling.pipeline_workers() == 2 and scheduling.pipeline_workers(4) == 1


def test_the_pipeline_asks_for_the_capped_host_processes(tmp_path, monkeypatch):
    """``run_campaign`` without ``workers``: the pipeline (a GPU campaign's way, here on the CPU) is handed
    ``pipeline_workers()`` processes, not every core."""
    from synthbos.benchmarks import campaign, scheduling

    class Asked(Exception):
        pass

    def fake_pipeline(renders, scores, *, workers, **kwargs):
        raise Asked(workers)

    monkeypatch.setattr(scheduling, "default_workers", lambda: 64)
    monkeypatch.setattr(campaign, "run_pipeline", fake_pipeline)
    with pytest.raises(Asked) as asked:
        run_campaign(SMALL, tmp_path / "c", device="cpu", progress=False, figures=False, pipeline=True)
    assert asked.value.args == (16,)


def test_prepared_inputs_read_the_pattern_ahead_with_the_same_result(pair_file):
    """A campaign reads the correlation's pattern where it draws the noisy images (``Method.prepare``);
    the item measured with those settings is the item measured alone, settings and vectors."""
    from synthbos.benchmarks.items import measure_item, prepared_inputs
    from synthbos.raytrace import read_pair

    pair = read_pair(pair_file)
    run = [(str(pair_file), "correlation", 2.0, (3, 4), "c.npz", {}, "cpu"),
           (str(pair_file), "tracking", 2.0, (3, 4), "t.npz", {}, "cpu")]
    images, settings = prepared_inputs(pair, run, run)
    assert list(settings) == [id(run[0])]  # tracking reads nothing ahead
    ahead_settings = settings[id(run[0])]
    assert ahead_settings.pattern == "random" and ahead_settings.device == "cpu"
    assert prepared_inputs(pair, run)[1] == {}  # nothing asked: nothing read
    ahead = measure_item(pair, *run[0], images=images, settings=ahead_settings)[2]
    alone = measure_item(pair, *run[0])[2]
    assert ahead.settings == alone.settings and ahead.settings["pattern"] == "random"
    assert ahead.uv.tobytes() == alone.uv.tobytes()
