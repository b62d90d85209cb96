"""Campaigns that track stacks of pairs (``benchmarks.stacks``, ``scheduling.run_pipeline(stack=...)``).

A GPU campaign tracks its tracking items in stacks by default; the CPU runs the same orchestration when
asked (``stack=N``, ``--stack N``), which is how these tests run it: a campaign run plain (item by item)
and stacked gives the same ``results.csv``, score arrays equal to 1e-9 px and tables equal dot by dot.
"""

import shutil
from dataclasses import replace

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal
from synthbos.benchmarks import stacks as stacks_module
from synthbos.benchmarks.campaign import run_campaign
from synthbos.benchmarks.cli import main
from synthbos.benchmarks.items import item_images, measure_item
from synthbos.benchmarks.registry import STACK_CPU_KERNELS, STACK_KERNELS, stack_settings
from synthbos.benchmarks.scheduling import campaign_kernels, same_image_runs, split_items, worker_kernels
from synthbos.benchmarks.spec import REGRESS
from synthbos.benchmarks.stacks import DEFAULT_STACK, Stacks, default_stack
from synthbos.benchmarks.storage import pair_path
from synthbos.raytrace import read_pair

from synthbos import SynthbosError

SMALL_CONFIG = {
    "camera": {"pixels": [96, 96]},
    "target": {"dots_per_32px": 12.0},
    "rays": {"per_dot": 10},
}
# Two pairs, two noise levels, every default method: 12 score items, 8 of them tracked.
SMALL = replace(REGRESS, name="small", snapshots=(1, 3), noise_percent=(0.0, 3.0), config=SMALL_CONFIG)
# Predictor columns: float32 correlations summed in another order by the two paths (tests/tracking/test_stack.py).
PREDICTOR = ("u_pred", "v_pred", "pred_correlation")


def _files(folder):
    return sorted(p.relative_to(folder) for p in folder.rglob("*") if p.is_file() and p.name != ".lock")


def _scores(folder):
    out = {}
    for path in sorted((folder / "scores").glob("*.npz")):
        with np.load(path) as z:
            out[path.name] = {k: z[k] for k in z.files}
    return out


def assert_same_scores(a, b, *, exact):
    """Score files of two campaign folders: the same arrays, bit for bit (``exact``) or to 1e-9."""
    sa, sb = _scores(a), _scores(b)
    assert sorted(sa) == sorted(sb) and len(sa) == 12
    for name in sa:
        assert sorted(sa[name]) == sorted(sb[name]), name
        for k, x in sa[name].items():
            y = sb[name][k]
            if exact or x.dtype.kind != "f":
                assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), (name, k)
            else:
                assert_array_equal(np.isnan(x), np.isnan(y), err_msg=f"{name} {k}")
                assert_allclose(x, y, rtol=0, atol=1e-9, err_msg=f"{name} {k}")


def assert_same_rows(rows_a, rows_b):
    """Two campaigns' results rows: the same counts and words, numbers equal to 1e-9 relative."""
    assert len(rows_a) == len(rows_b)
    for a, b in zip(rows_a, rows_b, strict=True):
        assert a.keys() == b.keys()
        for k in a:
            if isinstance(a[k], float):
                assert a[k] == pytest.approx(b[k], rel=1e-9, abs=1e-12, nan_ok=True), (a["method"], k)
            else:
                assert a[k] == b[k], k


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    """The campaign as the CPU runs it by default: item by item (one worker: in this process)."""
    folder = tmp_path_factory.mktemp("plain") / "c"
    rows = run_campaign(SMALL, folder, device="cpu", workers=1, progress=False, figures=False)
    return folder, rows


@pytest.fixture(scope="module")
def stacked(tmp_path_factory):
    """The same campaign with its tracking in stacks of both pairs, scored by one worker process."""
    folder = tmp_path_factory.mktemp("stacked") / "c"
    log = []
    rows = run_campaign(SMALL, folder, device="cpu", workers=2, progress=False, figures=False, stack=8, stacks=log)
    return folder, rows, log


def test_stacked_campaign_gives_the_plain_results(plain, stacked):
    (folder, rows), (sfolder, srows, log) = plain, stacked
    # one track_pairs call for both pairs' two noise levels; tracking and tracking-cc share its rows
    assert log == [{"pairs": 2, "images": 4, "device": "cpu"}]
    assert (sfolder / "results.csv").read_bytes() == (folder / "results.csv").read_bytes()
    assert_same_rows(srows, rows)
    assert _files(sfolder) == _files(folder)
    assert_same_scores(folder, sfolder, exact=False)


def test_stacked_tables_equal_the_item_by_item_tables(plain):
    """Each stacked item's result (a row of its image pair's track_pairs table) against ``measure_item``'s
    (``track_pair``): the same status bits, positions and displacements to 1e-9 px."""
    folder, _ = plain
    items = []
    for s, p in SMALL.pair_keys():
        path = str(pair_path(folder, s, p))
        for noise in SMALL.noise_percent:
            seeds = (SMALL.noise_seed(s, p, noise, "reference"), SMALL.noise_seed(s, p, noise, "gradient"))
            items += [(path, m, noise, seeds, f"{s}{p}{noise}{m}.npz", {}, "cpu") for m in SMALL.methods]
    here, stacked, there = split_items(items, stack=8)
    assert {a[1] for a in stacked} == {"tracking", "tracking-cc"} and [a[1] for a in here] == ["correlation"] * 4
    assert there == []
    stacks = Stacks(8)
    for path in dict.fromkeys(a[0] for a in stacked):
        pair = read_pair(path)
        runs = same_image_runs([a for a in stacked if a[0] == path])
        stacks.add(path, pair, [(item_images(pair, run[0]), run) for run in runs])
    stacks.flush()
    measured = [host for _, hosts in stacks.take() for host in hosts]
    assert [h[3] for h in measured] == [a[4] for a in stacked]
    for host, args in zip(measured, stacked, strict=True):
        one = measure_item(read_pair(args[0]), *args)[2]
        got = host[2]
        assert got.method == one.method and got.settings == one.settings and got.counts == one.counts
        assert_array_equal(got.valid, one.valid)
        assert_array_equal(got.table["status"], one.table["status"])
        assert_array_equal(np.isnan(got.uv), np.isnan(one.uv))
        assert_allclose(got.uv, one.uv, rtol=0, atol=1e-9)
        for k, col in one.table.items():
            col, mine = np.asarray(col), np.asarray(got.table[k])
            if col.dtype.kind == "f":
                assert_array_equal(np.isnan(mine), np.isnan(col), err_msg=k)
                assert_allclose(mine, col, rtol=0, atol=1e-5 if k in PREDICTOR else 1e-9, err_msg=k)
            else:
                assert_array_equal(mine, col, err_msg=k)


def test_stacks_of_one_pair_give_the_same_results_and_a_stacked_run_resumes(stacked, tmp_path):
    """A pair's results do not depend on what else its stack holds (to rounding: the fit's fixed-point scale
    is the stack's): stacks of one pair, in this process, give the results of stacks of two; an interrupted
    stacked run, run again, stacks only the missing items and ends with the same results, keeping the
    files it had."""
    sfolder, srows, _ = stacked
    log = []
    ones = run_campaign(SMALL, tmp_path / "one", device="cpu", workers=1, progress=False, figures=False, stack=1,
                        stacks=log)
    assert log == [{"pairs": 1, "images": 2, "device": "cpu"}] * 2
    assert (tmp_path / "one" / "results.csv").read_bytes() == (sfolder / "results.csv").read_bytes()
    assert_same_rows(ones, srows)
    assert_same_scores(sfolder, tmp_path / "one", exact=False)
    resumed = tmp_path / "r"
    shutil.copytree(sfolder, resumed)
    for p in [*sorted((resumed / "scores").glob("*tracking*.npz"))[::3], next((resumed / "pairs").glob("*.h5"))]:
        p.unlink()
    kept = {p: p.stat().st_mtime_ns for p in (resumed / "scores").glob("*.npz")}
    log = []
    again = run_campaign(SMALL, resumed, device="cpu", workers=1, progress=False, figures=False, stack=8, stacks=log)
    assert sum(e["images"] for e in log) == 3  # the noisy image pairs of the 3 missing items
    assert {p: p.stat().st_mtime_ns for p in kept} == kept
    assert (resumed / "results.csv").read_bytes() == (sfolder / "results.csv").read_bytes()
    assert_same_rows(again, srows)
    assert_same_scores(sfolder, resumed, exact=False)


def test_an_error_in_a_stacked_run_loses_only_unwritten_items(stacked, tmp_path, monkeypatch):
    import synthbos.benchmarks.items as items

    sfolder, srows, _ = stacked
    out = tmp_path / "c"
    finish, done = items.finish_item, []

    def failing(*args, **kw):
        if len(done) == 5:
            raise RuntimeError("scoring failed")
        done.append(finish(*args, **kw))
        return done[-1]

    monkeypatch.setattr(items, "finish_item", failing)
    with pytest.raises(RuntimeError, match="scoring failed"):
        run_campaign(SMALL, out, device="cpu", workers=1, progress=False, figures=False, stack=8)
    assert sorted(p.name for p in (out / "scores").glob("*.npz")) == sorted(a.rsplit("/", 1)[1] for a in done)
    assert not list(out.rglob("*.tmp"))
    monkeypatch.setattr(items, "finish_item", finish)
    assert_same_rows(run_campaign(SMALL, out, device="cpu", workers=1, progress=False, figures=False, stack=8), srows)
    assert (out / "results.csv").read_bytes() == (sfolder / "results.csv").read_bytes()
    assert_same_scores(sfolder, out, exact=False)


def _items(device, methods=("correlation", "tracking", "tracking-cc", "tracking-paper")):
    return [("p.h5", m, 1.0, (1, 2), f"{m}.npz", {}, device) for m in methods]


def test_stack_kernels_are_the_modules_track_pairs_launches(monkeypatch):
    """STACK_CPU_KERNELS (the modules a stacked campaign builds ahead on the CPU; STACK_KERNELS on a GPU,
    checked by tests/test_cuda_build.py) names every Python module whose Warp kernels ``track_pairs``
    launches on the CPU, and no other (the modules were renamed by step: a stale name would build nothing,
    a missing one would compile during the work)."""
    import warp as wp
    from synthbos.raytrace.dots import draw_dots
    from synthbos.tracking.stack import track_pairs

    from synthbos.device import _warp_modules

    launched = set()
    for name in ("launch", "launch_tiled"):
        original = getattr(wp, name)

        def spy(kernel, *args, _original=original, **kwargs):
            launched.add((kernel.func.__module__, kernel.module.name))
            return _original(kernel, *args, **kwargs)

        monkeypatch.setattr(wp, name, spy)
    rng = np.random.default_rng(4)
    shape = (64, 64)
    xy = rng.uniform(4.0, 60.0, (60, 2))
    refs = np.stack([draw_dots(shape, xy, 3.0), draw_dots(shape, xy, 3.0)])
    grads = np.stack([draw_dots(shape, xy + 0.7, 3.0), draw_dots(shape, xy - 0.4, 3.0)])
    track_pairs(refs, grads, prior_xy=xy + 0.2, device="cpu")
    assert {name for name, _ in launched} == set(STACK_CPU_KERNELS)
    # and only the Warp modules those names build: no step's GPU engine (``GPU_MODULE``) on the CPU
    built = {m.name for name in STACK_CPU_KERNELS for m in _warp_modules(name)}
    assert {module for _, module in launched} <= built
    assert not any(module.endswith(".gpu") for module in built)


def test_stacks_hold_the_trackers_whose_identification_is_kernels_and_load_their_kernels():
    run = _items("cuda:0")
    here, stacked, there = split_items(run, worker_device="cpu", stack=8)
    assert [a[1] for a in here] == ["correlation"] and [a[1] for a in stacked] == ["tracking", "tracking-cc"]
    # the paper's procedure identifies its dots with host code: item by item (a stack of one), in the workers
    assert there == [(*run[3][:-1], "cpu")]
    assert split_items(run, stack=0)[1] == [] and stack_settings("tracking", {"centroid": "gaussian3"}) is None
    # the device process loads track_pairs's kernels on the processing device; the workers, those they launch
    kernels = campaign_kernels([], run, worker_device="cpu", stack=8)
    assert {(k, "cuda:0") for k in STACK_KERNELS} <= set(kernels)
    assert {d for _, d in worker_kernels(run, worker_device="cpu", stack=8)} == {"cpu"}
    assert worker_kernels(_items("cuda:0", ("tracking", "tracking-cc")), worker_device="cpu", stack=8) == []
    # by default: stacks where tracking runs on a GPU, item by item on the CPU
    assert default_stack(run) == DEFAULT_STACK and default_stack(_items("cpu")) == 0
    assert default_stack(_items("cuda:0", ("correlation",))) == 0


def test_a_gpu_stack_is_one_track_pairs_call_on_the_processing_device(plain, monkeypatch):
    """The GPU path is the CPU's with another device string: one call per stack on the items' device, bounded
    by what the device holds (``pairs_per_call``); each call tracks on the CPU here."""
    folder, _ = plain
    calls = []

    def track_pairs(refs, grads, *, prior_xy, settings, device):
        calls.append((len(refs), device))
        return real(refs, grads, prior_xy=prior_xy, settings=settings, device="cpu")

    real = stacks_module.track_pairs
    monkeypatch.setattr(stacks_module, "track_pairs", track_pairs)
    limits = []
    monkeypatch.setattr(stacks_module, "pairs_per_call",
                        lambda shape, dots, device, on_device: limits.append(device) or 3)
    pairs = [read_pair(p) for p in sorted((folder / "pairs").glob("*.h5"))]
    stacks = Stacks(8)
    for k, pair in enumerate(pairs * 2):  # four pairs of two noisy image pairs each: 3 fit a call, so 2 per call
        runs = [(None, [(f"p{k}", m, noise, (k, int(noise)), f"{k}{noise}{m}", {}, "cuda:0")
                        for m in ("tracking", "tracking-cc")]) for noise in (0.0, 3.0)]
        stacks.add(k, pair, runs)
    stacks.flush()
    assert calls == [(2, "cuda:0")] * 4 and set(limits) == {"cuda:0"}
    taken = stacks.take()
    assert [tag for tag, _ in taken] == [0, 0, 1, 1, 2, 2, 3, 3]
    assert all(len(hosts) == 2 and {h[-1] for h in hosts} == {"cuda:0"} for _, hosts in taken)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["paper", "--quick", "--device", "cpu", "--methods", "correlation", "--stack", "4", "-o", "camp"],
         "--stack 4: none of the methods (correlation) is tracked in stacks"),
        (["paper", "--quick", "--device", "cpu", "--scheduler", "local", "--stack", "2", "-o", "camp"],
         "--stack 2: with --scheduler on CPU workers each pair is a task of its own"),
        (["sweep", "--param", "noise=0", "--device", "cpu", "--methods", "tracking-paper", "--stack", "2", "-o", "sw"],
         "--stack 2: none of the methods (tracking-paper) is tracked in stacks"),
        (["regress", "--methods", "correlation", "--stack", "2", "-o", "rg"],
         "--stack 2: none of the methods (correlation) is tracked in stacks"),
    ],
)
def test_stacks_that_make_no_sense_are_refused(tmp_path, monkeypatch, capsys, argv, message):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert list(tmp_path.iterdir()) == []


def test_a_negative_stack_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["paper", "--quick", "--stack", "-1"])
    assert exit_.value.code == 2 and "--stack: must be 0 (item by item) or more pairs" in capsys.readouterr().err


def test_the_stack_option_reaches_the_campaigns(tmp_path, monkeypatch, capsys):
    from synthbos.benchmarks import cli, sweep

    seen = []

    def campaign(spec, out, *, stack, stacks, **kwargs):
        seen.append(stack)
        stacks.append({"pairs": 3, "images": 12, "device": "cpu"})
        return []

    monkeypatch.setattr(cli, "run_campaign", campaign)
    monkeypatch.setattr(cli, "format_summary", lambda rows: "")
    assert main(["paper", "--quick", "--device", "cpu", "--stack", "3", "-q", "-o", str(tmp_path / "p")]) == 0
    assert main(["paper", "--quick", "--device", "cpu", "-q", "-o", str(tmp_path / "q")]) == 0
    out = capsys.readouterr().out
    assert seen == [3, None]
    assert "tracking in stacks: 1 track_pairs call on cpu, up to 3 pairs (12 image pairs) per call (stack 3)" in out
    monkeypatch.setattr(sweep, "run_sweep", lambda *a, stack, stacks, **kw: seen.append(stack) or [])
    assert main(["sweep", "--param", "noise=0", "--device", "cpu", "--stack", "0", "-q", "-o",
                 str(tmp_path / "s")]) == 0
    monkeypatch.setattr(cli, "run_regress", lambda *, stack, stacks, **kw: (seen.append(stack), ([], []))[1])
    assert main(["regress", "--stack", "5", "-q"]) == 0
    assert seen == [3, None, 0, 5]


def test_the_library_refuses_stacks_without_the_pipeline(tmp_path):
    with pytest.raises(SynthbosError, match="pipeline=False"):
        run_campaign(SMALL, tmp_path / "c", device="cpu", workers=1, progress=False, figures=False, stack=2,
                     pipeline=False)
    with pytest.raises(SynthbosError, match="whole number"):
        run_campaign(SMALL, tmp_path / "c", device="cpu", progress=False, stack=2.5)
    assert not (tmp_path / "c").exists()


def test_the_stack_reaches_dask_pipeline_tasks(monkeypatch):
    """``run_pairs(stack=...)`` reaches each GPU worker's pipeline task and its ``run_pipeline``; workers that run
    one task per pair refuse a stack."""
    pytest.importorskip("distributed")
    from synthbos.benchmarks import distributed as dist

    submitted = []

    class Client:
        def nthreads(self):
            return {"tcp://a": 1, "tcp://b": 1}

        def submit(self, fn, *args, **kwargs):
            submitted.append((fn, kwargs.get("stack")))
            return object()

    runner = dist.DaskRunner("local", device="cuda:0", pipeline=True)
    runner.client = Client()
    tasks = [(("cfg", f"p{i}.h5", "cuda:0"), [(f"p{i}.h5", "tracking")]) for i in range(3)]
    assert len(runner._submit(tasks, "token", 4)) == 2
    assert submitted == [(dist.pipeline_task, 4)] * 2
    seen = []
    monkeypatch.setattr(dist, "run_pipeline", lambda renders, scores, *, stack, **kw: seen.append(stack))
    dist.pipeline_task([], [], "token", stack=4)
    dist.pipeline_task([], [], "token")
    assert seen == [4, None]
    with pytest.raises(SynthbosError, match="--stack 2: these Dask workers run one task per pair"):
        dist.DaskRunner("local", device="cpu").run_pairs([], [], stack=2)



@pytest.mark.slow
def test_a_stacked_campaign_on_a_local_dask_cluster(slow_only, plain, tmp_path):
    """Pipeline tasks on a local cluster (each holding every second pair) track their pairs in stacks: the
    plain run's results.csv, and the score files of a run in one process with stacks of one pair each.
    On the CPU a stack equals ``track_pair`` bit for bit (its host engines), so the item-by-item scores
    are the same too; that the stack reaches the tasks is :func:`test_the_stack_reaches_dask_pipeline_tasks`'s."""
    pytest.importorskip("distributed")
    from synthbos.benchmarks.distributed import DaskRunner

    folder, _ = plain
    ones = tmp_path / "one"
    run_campaign(SMALL, ones, device="cpu", workers=1, progress=False, figures=False, stack=1)
    with DaskRunner("local", device="cpu", workers=2, progress=False, pipeline=True) as runner:
        run_campaign(SMALL, tmp_path / "dask", device="cpu", scheduler=runner, progress=False, figures=False, stack=8)
    assert (tmp_path / "dask" / "results.csv").read_bytes() == (folder / "results.csv").read_bytes()
    assert_same_scores(ones, tmp_path / "dask", exact=True)
    assert_same_scores(folder, tmp_path / "dask", exact=True)


@pytest.mark.gpu
def test_a_gpu_campaign_stacks_by_default_and_gives_the_item_by_item_results(tmp_path):
    """On a GPU the pipeline stacks by default; item by item with the tracking workers on the same GPU
    (``--stack 0 --worker-device cuda:0``) it gives the same results.csv and score arrays to 1e-9 px."""
    log = []
    stacked = run_campaign(SMALL, tmp_path / "s", device="cpu", process_device="cuda:0", workers=2, progress=False,
                           figures=False, stacks=log)
    assert log == [{"pairs": 2, "images": 4, "device": "cuda:0"}]
    one_by_one = run_campaign(SMALL, tmp_path / "i", device="cpu", process_device="cuda:0", workers=2,
                              progress=False, figures=False, stack=0, worker_device="cuda:0")
    assert {r["process_device"] for r in stacked} == {"cuda:0"}
    assert (tmp_path / "s" / "results.csv").read_bytes() == (tmp_path / "i" / "results.csv").read_bytes()
    assert_same_rows(stacked, one_by_one)
    assert_same_scores(tmp_path / "i", tmp_path / "s", exact=False)
