"""A campaign builds the Warp modules its items launch, each once, in its pool's processes, before the items
(``scheduling.build_in_pool``); the lists come from the registry (``Method.kernels_on``) and the renderer
(``raytrace.render_modules``)."""

import os
from concurrent.futures import Future, ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

from synthbos.benchmarks.registry import get_method
from synthbos.benchmarks.scheduling import (
    build_in_pool,
    campaign_kernels,
    render_kernels,
    run_items,
    score_kernels,
    submit_builds,
    worker_pool,
)

from synthbos.shipped_kernels import DISABLE_ENV


def test_methods_name_the_kernels_they_launch_on_each_device():
    corr, track = get_method("correlation"), get_method("tracking")
    assert corr.kernels_on("cpu") == ("synthbos.correlation.kernels",)
    assert corr.kernels_on(None) == corr.kernels_on("cpu")
    assert corr.kernels_on("cuda:0") == ("synthbos.correlation.kernels", "synthbos.correlation.pass_kernels",
                                         "synthbos.correlation.line_kernels")
    assert "synthbos.tracking.deform_kernels" in track.kernels_on("cuda:0")
    assert "synthbos.tracking.deform_kernels" not in track.kernels_on("cpu")
    assert set(track.kernels_on("cpu")) < set(track.kernels)


def test_item_lists_give_each_module_once_per_device():
    cfg = {"camera": {"pixels": [64, 64]}}
    renders = [(cfg, "a.h5", "cpu"), ({**cfg, "rays": {"field": "float32"}}, "b.h5", "cpu"), (cfg, "c.h5", None)]
    base, truth = "synthbos.raytrace.kernels.", "synthbos.raytrace.truth_kernels."
    assert render_kernels(renders) == [(base + n, "cpu") for n in (
        "render_Medium", "render_MediumStraight", "render_MediumVec")] + [
        (truth + n, "cpu") for n in ("truth_Medium", "truth_MediumVec")]
    scores = [("a.h5", m, 1.0, (1, 2), "out", {}, "cpu") for m in ("correlation", "tracking", "tracking-cc")]
    scores.append(("a.h5", "correlation", 1.0, (1, 2), "out", {}, None))  # no device: nothing to build
    assert score_kernels(scores) == [("synthbos.correlation.kernels", "cpu"),
                                     *[(f"synthbos.tracking.{n}_kernels", "cpu")
                                       for n in ("claim", "ellipse", "fit", "identify", "kernel_step", "moment",
                                                 "neighbour", "stats", "table", "wide_search")]]
    both = campaign_kernels(renders, scores)
    assert both == sorted(render_kernels(renders) + score_kernels(scores))


def test_the_pool_builds_each_named_module_and_only_those(tmp_path, monkeypatch):
    cache = tmp_path / "kernels"
    monkeypatch.setenv("WARP_CACHE_PATH", str(cache))  # the spawned processes' own, empty kernel cache
    monkeypatch.setenv(DISABLE_ENV, "0")  # and none of the shipped CPU kernels copied into it
    wanted = ["synthbos.tracking.moment_kernels", "synthbos.tracking.neighbour_kernels"]
    with ProcessPoolExecutor(2, mp_context=get_context("spawn")) as pool:
        build_in_pool(pool, [(name, "cpu") for name in wanted])
        pids = {pool.submit(os.getpid).result() for _ in range(4)}
    built = sorted(p.name for p in Path(cache).rglob("wp_synthbos.*") if p.is_dir() and list(p.glob("*.o")))
    assert [b.rsplit("_", 1)[0] for b in built] == [f"wp_{name}" for name in wanted]
    assert len(pids) <= 2


class _CountingPool:
    """Stands in for a process pool: records what it is handed, runs nothing."""

    def __init__(self):
        self.handed = []

    def submit(self, fn, *args, **kwargs):
        self.handed.append(args[0])
        return Future()


def test_a_module_handed_to_a_pool_once_is_not_handed_again():
    pool, other = _CountingPool(), _CountingPool()
    a, b = ("synthbos.tracking.moment_kernels", "cpu"), ("synthbos.tracking.fit_kernels", "cpu")
    first = submit_builds(pool, [a])
    both = submit_builds(pool, [b, a])
    assert pool.handed == [[a], [b]]
    assert both[1] is first[0]  # the build in flight, waited for instead of a second one beside it
    submit_builds(other, [a])
    assert other.handed == [[a]]  # another pool's processes build their own


def test_one_pool_runs_two_calls_and_builds_the_next_calls_kernels_after_the_items(tmp_path, monkeypatch):
    cache = tmp_path / "kernels"
    monkeypatch.setenv("WARP_CACHE_PATH", str(cache))
    monkeypatch.setenv(DISABLE_ENV, "0")
    monkeypatch.setattr("synthbos.benchmarks.drivers.get_context", lambda method: get_context("spawn"))
    later = [("synthbos.tracking.moment_kernels", "cpu")]
    with worker_pool(2) as pool:
        run_items([(-3,), (4,)], abs, workers=2, desc="", progress=False, pool=pool, build_after=later)
        assert not list(Path(cache).rglob("wp_synthbos.tracking.neighbour_kernels*"))
        run_items([(5,)], abs, workers=2, desc="", progress=False, pool=pool, kernels=later)
        assert pool.submit(abs, -2).result() == 2  # still open after both calls
    built = [p.name for p in Path(cache).rglob("wp_synthbos.*") if p.is_dir() and list(p.glob("*.o"))]
    assert [b.rsplit("_", 1)[0] for b in built] == ["wp_synthbos.tracking.moment_kernels"]
    with worker_pool(1) as none:
        assert none is None
