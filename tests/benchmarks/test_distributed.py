"""Campaigns on a Dask cluster give the files of a run in one process, byte for byte, and survive a dead worker.

Every test runs the same tiny sweep (two noise levels, each point a campaign of two 96 x 96 pairs and
all three methods) and compares its folder with the same sweep run in this process: the tables byte
for byte, every score array and every pair dataset bit for bit. (Pair files store the render's wall
time and score files are zip archives stamped with their write time, so those two kinds of file are
compared by content, not as raw bytes.)
"""

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

distributed = pytest.importorskip("distributed")

from synthbos.benchmarks.cli import main  # noqa: E402
from synthbos.benchmarks.distributed import TASK_PREFIX, _pair_tasks  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
BASE_TOML = '[camera]\npixels = [96, 96]\n[rays]\nper_dot = 20\n[target]\ndots_per_32px = 12.0\n'
FIGURES = (".png", ".pdf", ".svg")  # drawings, stamped with their creation date
SWEEP = ["--param", "noise=0,3", "--size", "regress", "--device", "cpu", "-q"]


def _sweep(folder, *extra):
    cfg = Path(folder).parent / "base.toml"
    cfg.write_text(BASE_TOML)
    assert main(["sweep", str(cfg), *SWEEP, "--out", str(folder), *extra]) == 0


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    """The sweep run in this process, one item after the other: the reference."""
    folder = tmp_path_factory.mktemp("plain") / "sweep"
    _sweep(folder, "--workers", "1")
    return folder


def _pair_datasets(path):
    with h5py.File(path) as f:
        out = {}
        f.visititems(lambda name, obj: out.update({name: obj[()]}) if isinstance(obj, h5py.Dataset) else None)
        attrs = {k: v for k, v in f.attrs.items() if k != "render_seconds"}
    return out, attrs


def assert_same_results(a: Path, b: Path) -> None:
    """Folder ``b`` holds exactly the results of folder ``a``."""
    for name in ("sweep.csv", "sweep.json"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    files_a = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file() and p.suffix not in FIGURES)
    files_b = sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file() and p.suffix not in FIGURES)
    assert files_a == files_b  # the same layout, and no temporary file left behind
    assert any(p.suffix == ".npz" for p in files_a) and any(p.suffix == ".h5" for p in files_a)
    for rel in files_a:
        if rel.suffix == ".npz":
            with np.load(a / rel) as za, np.load(b / rel) as zb:
                assert sorted(za.files) == sorted(zb.files)
                for k in za.files:
                    assert za[k].dtype == zb[k].dtype and za[k].tobytes() == zb[k].tobytes(), (rel, k)
        elif rel.suffix == ".h5":
            (da, attrs_a), (db, attrs_b) = _pair_datasets(a / rel), _pair_datasets(b / rel)
            assert attrs_a == attrs_b and sorted(da) == sorted(db)
            for k in da:
                same = (da[k].tolist() == db[k].tolist() if np.asarray(da[k]).dtype == object  # text labels
                        else da[k].tobytes() == db[k].tobytes())
                assert da[k].dtype == db[k].dtype and same, (rel, k)
        else:  # campaign.json, results.csv, results.json, sweep_params.json
            assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel


def test_pair_tasks_group_items_by_pair():
    renders = [({"c": 1}, "/f/pairs/s1_p00.h5", "cpu")]
    scores = [(f"/f/pairs/s{s}_p00.h5", m, 0.0, (1, 2), f"/f/scores/s{s}_{m}.npz", {}) for s in (1, 2)
              for m in ("a", "b")]
    tasks = _pair_tasks(renders, scores)
    assert [(r is not None, [s[1] for s in items]) for r, items in tasks] == [(True, ["a", "b"]), (False, ["a", "b"])]


def test_local_gpu_workers_are_pinned_one_per_gpu():
    from synthbos.benchmarks.distributed import DaskRunner

    def pins(**kw):
        specs = DaskRunner("local", device="cuda:0", **kw).local_worker_specs(distributed)
        assert all(s["options"]["nthreads"] == 1 for s in specs.values())
        return {name: s["options"]["env"]["CUDA_VISIBLE_DEVICES"] for name, s in specs.items()}

    assert pins(gpus=["0", "1", "2", "3"], workers=4) == {"gpu0": "0", "gpu1": "1", "gpu2": "2", "gpu3": "3"}
    # by default LOCAL_WORKERS_PER_GPU (two) pipelines share each GPU
    assert pins(gpus=["0", "1"]) == {"gpu0-0": "0", "gpu1-1": "1", "gpu0-2": "0", "gpu1-3": "1"}
    assert pins(gpus=["2", "3"], workers=3) == {"gpu2-0": "2", "gpu3-1": "3", "gpu2-2": "2"}
    cpu = DaskRunner("local", device="cpu", workers=2).local_worker_specs(distributed)
    assert list(cpu) == ["cpu0", "cpu1"]
    assert all("CUDA_VISIBLE_DEVICES" not in s["options"]["env"] for s in cpu.values())
    with pytest.raises(ValueError, match="its own GPU"):
        DaskRunner("local", device="cuda:1", gpus=["0"]).local_worker_specs(distributed)


def test_local_workers_share_the_cores(monkeypatch):
    # every GPU worker's BLAS/OpenMP pool gets the cores of one GPU's share of the host, however many
    # of the GPUs a run uses, so that weak scaling compares like with like; CPU workers split the host
    from synthbos.benchmarks import distributed as dist

    monkeypatch.setattr(dist, "default_workers", lambda: 64)
    monkeypatch.setattr(dist, "visible_gpus", lambda: ["0", "1", "2", "3"])

    def share(device, **kw):
        specs = dist.DaskRunner("local", device=device, **kw).local_worker_specs(distributed).values()
        return {s["options"]["env"][var] for s in specs for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS")}

    assert {n: share("cuda:0", gpus=["0", "1", "2", "3"][:n], workers=n) for n in (1, 2, 4)} == {
        1: {"16"}, 2: {"16"}, 4: {"16"}}
    # two workers per GPU (the default): half a GPU's share each, on 1, 2 or 4 of the GPUs
    assert {n: share("cuda:0", gpus=["0", "1", "2", "3"][:n]) for n in (1, 2, 4)} == {1: {"8"}, 2: {"8"}, 4: {"8"}}
    assert share("cuda:0", gpus=["0", "1"], workers=8) == {"4"}  # four to a GPU: a quarter of its 16 cores
    assert share("cpu", workers=8) == {"8"}


def test_host_processes_per_gpu_worker_can_be_told(monkeypatch):
    # each local GPU worker's pool of host processes: its share of the cores (at most 16), or the user's
    # SYNTHBOS_HOST_WORKERS; anything but a positive number is refused in one line
    from synthbos.benchmarks import distributed as dist

    from synthbos import SynthbosError

    monkeypatch.setattr(dist, "default_workers", lambda: 64)
    monkeypatch.setattr(dist, "visible_gpus", lambda: ["0", "1", "2", "3"])

    def told():
        specs = dist.DaskRunner("local", device="cuda:0").local_worker_specs(distributed).values()
        return {s["options"]["env"][dist.HOST_WORKERS_VAR] for s in specs}

    monkeypatch.delenv(dist.HOST_WORKERS_VAR, raising=False)
    assert told() == {str(dist.pipeline_workers(4 * dist.LOCAL_WORKERS_PER_GPU))}
    monkeypatch.setenv(dist.HOST_WORKERS_VAR, "6")
    assert told() == {"6"}
    for bad in ("0", "-2", "many"):
        monkeypatch.setenv(dist.HOST_WORKERS_VAR, bad)
        with pytest.raises(SynthbosError, match="positive number of host processes"):
            told()
        with pytest.raises(SynthbosError, match="positive number of host processes"):
            dist.check_scheduler("local")  # before any work


def test_a_worker_reads_host_workers_by_the_runners_rule(monkeypatch):
    """``host_workers`` on a worker takes the variable where it is a positive number and refuses anything
    else as the runner does; unset, this host's cores over its GPUs."""
    from synthbos.benchmarks import distributed as dist

    from synthbos import SynthbosError

    monkeypatch.setenv(dist.HOST_WORKERS_VAR, " 7 ")
    assert dist.host_workers() == 7
    monkeypatch.setenv(dist.HOST_WORKERS_VAR, "0")
    with pytest.raises(SynthbosError, match="positive number of host processes"):
        dist.host_workers()
    monkeypatch.delenv(dist.HOST_WORKERS_VAR)
    assert dist.host_workers() == dist.pipeline_workers(len(dist.visible_gpus()))


def test_a_bad_host_workers_value_is_one_line_and_writes_nothing(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("SYNTHBOS_HOST_WORKERS", "lots")
    out = tmp_path / "q"
    assert main(["paper", "--quick", "-q", "-o", str(out), "--scheduler", "local"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "SYNTHBOS_HOST_WORKERS='lots'" in err[0]
    assert not out.exists()


def test_scheduler_errors_are_one_line(tmp_path, capsys):
    cfg = tmp_path / "base.toml"
    cfg.write_text(BASE_TOML)
    for scheduler, message in (("nonsense", "--scheduler must be"), (str(tmp_path / "no.json"), "does not exist")):
        assert main(["sweep", str(cfg), *SWEEP, "--out", str(tmp_path / "s"), "--scheduler", scheduler]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0]


def test_synthbos_imports_without_dask():
    code = "import sys, synthbos.benchmarks.cli; sys.exit('distributed' in sys.modules or 'dask' in sys.modules)"
    subprocess.run([sys.executable, "-c", code], check=True, env={**os.environ, "PYTHONPATH": str(ROOT)})


def test_local_cluster_of_two_workers_matches_plain_run_and_resumes(plain, tmp_path):
    out = tmp_path / "sweep"
    shutil.copytree(plain, out)  # a sweep stopped part-way: one pair and some scores are missing
    for p in (out / "sweep.json", out / "sweep.csv", next((out / "points").glob("noise=3/pairs/*.h5"))):
        p.unlink()
    for p in sorted((out / "points").glob("*/scores/*.npz"))[::2]:
        p.unlink()
    _sweep(out, "--scheduler", "local", "--workers", "2")
    assert_same_results(plain, out)


def _start(args, log):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, "-m", *args], env=env, stdout=log, stderr=subprocess.STDOUT)


@pytest.fixture(scope="module")
def external_cluster(tmp_path_factory):
    """A scheduler and two single-threaded workers (with their nannies), each its own process on 127.0.0.1."""
    tmp = tmp_path_factory.mktemp("cluster")
    sched_file = tmp / "scheduler.json"
    log = open(tmp / "cluster.log", "w")
    procs = [_start(["distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                     "--scheduler-file", str(sched_file)], log)]
    procs += [_start(["distributed.cli.dask_worker", "--scheduler-file", str(sched_file), "--host", "127.0.0.1",
                      "--nthreads", "1", "--no-dashboard", "--name", f"w{i}", "--local-directory", str(tmp / f"w{i}")],
                     log) for i in range(2)]
    try:
        deadline = time.monotonic() + 60
        while not sched_file.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        with distributed.Client(scheduler_file=str(sched_file), timeout="60s") as client:
            client.wait_for_workers(2, timeout=60)
        yield sched_file
    finally:
        for p in reversed(procs):  # workers first, then the scheduler
            p.terminate()
            try:
                p.wait(timeout=15)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        log.close()


def test_scheduler_and_workers_as_separate_processes_match_plain_run(plain, external_cluster, tmp_path):
    address = json.loads(external_cluster.read_text())["address"]
    assert address.startswith("tcp://127.0.0.1:")
    out = tmp_path / "sweep"
    _sweep(out, "--scheduler", address)
    assert_same_results(plain, out)


def test_an_error_in_a_task_stops_the_run_with_that_error(external_cluster, tmp_path, capsys):
    cfg = tmp_path / "base.toml"
    cfg.write_text(BASE_TOML)
    args = ["sweep", str(cfg), "--param", "window=16,0", "--device", "cpu", "-q", "--out", str(tmp_path / "s"),
            "--scheduler", str(external_cluster)]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "window size 0" in err[0]


@contextlib.contextmanager
def _worker_plugin(client, plugin, name: str):
    """``plugin`` on every worker of ``client``'s cluster while the block runs (sent by value: the workers
    cannot import this module)."""
    import cloudpickle

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    try:
        client.register_plugin(plugin, name=name)
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
    try:
        yield
    finally:
        client.unregister_worker_plugin(name)


class KillOnce(distributed.WorkerPlugin):
    """Kills the first worker that starts a pair task, once that task has written its first score file."""

    def __init__(self, marker, folder):
        self.marker, self.folder = str(marker), Path(folder)

    def transition(self, key, start, finish, **kwargs):
        if finish != "executing" or not str(key).startswith(TASK_PREFIX):
            return
        try:
            os.close(os.open(self.marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
        except FileExistsError:
            return
        stem = str(key)[len(TASK_PREFIX) + 1:].rsplit("-", 1)[0]  # the task's pair, s{S}_p{P}
        before = set(self.folder.glob("points/*/scores/*.npz"))
        threading.Thread(target=self._kill_after_first_score, args=(stem, before), daemon=True).start()

    def _kill_after_first_score(self, stem, before):
        while not (set(self.folder.glob(f"points/*/scores/{stem}_*.npz")) - before):
            time.sleep(0.002)
        done = [str(p) for p in self.folder.glob("points/*/*/*") if p.suffix in (".npz", ".h5")]
        Path(self.marker).write_text(json.dumps({"pid": os.getpid(), "done": done}))
        os.kill(os.getpid(), signal.SIGKILL)


def test_a_worker_killed_mid_campaign_loses_only_its_item(plain, external_cluster, tmp_path):
    import psutil

    out = tmp_path / "sweep"
    marker = tmp_path / "killed.json"
    with distributed.Client(scheduler_file=str(external_cluster)) as client, \
            _worker_plugin(client, KillOnce(marker, out), "kill-once"):
        _sweep(out, "--scheduler", str(external_cluster))
    killed = json.loads(marker.read_text())
    assert not psutil.pid_exists(killed["pid"])
    # The other worker finished the pair task in flight, and rewrote none of the files already there.
    for path in killed["done"]:
        assert Path(path).stat().st_mtime_ns <= marker.stat().st_mtime_ns
    assert_same_results(plain, out)



def _snapshot(folder):
    return {p: p.stat().st_mtime_ns for p in Path(folder).rglob("*") if p.is_file()}


def _interrupt_sweep(tmp_path, scheduler, *, group):
    """Start a longer sweep on ``scheduler``, press Ctrl-C once it has written scores; return its folder."""
    cfg = tmp_path / "base.toml"
    cfg.write_text(BASE_TOML)
    out = tmp_path / "sweep"
    args = ["synthbos", "sweep", str(cfg), "--param", "noise=0,1,2,3,4,5", "--size", "quick", "--device", "cpu",
            "-q", "--out", str(out), "--scheduler", scheduler, "--workers", "2"]
    proc = subprocess.Popen([sys.executable, "-m", *args], env={**os.environ, "PYTHONPATH": str(ROOT)},
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True, text=True)
    deadline = time.monotonic() + 300
    while not list(out.glob("points/*/scores/*.npz")) and time.monotonic() < deadline:
        time.sleep(0.05)
    # A terminal's Ctrl-C reaches its whole process group: a local cluster's workers too.
    (os.killpg if group else os.kill)(proc.pid, signal.SIGINT)
    output, _ = proc.communicate(timeout=120)
    assert proc.returncode == 130, output
    assert "interrupted" in output
    return out


@pytest.mark.slow
def test_ctrl_c_on_a_local_cluster_leaves_nothing_running(slow_only, tmp_path):
    import psutil

    out = _interrupt_sweep(tmp_path, "local", group=True)
    mine = [p for p in psutil.process_iter(["cmdline"]) if str(out) in " ".join(p.info["cmdline"] or [])]
    assert not mine
    before = _snapshot(out)
    time.sleep(3)
    assert _snapshot(out) == before
    assert len(list(out.glob("points/*/scores/*.npz"))) < 6 * 10 * 3  # it did stop part-way


@pytest.mark.slow
def test_ctrl_c_on_a_joined_cluster_waits_for_the_items_in_flight(slow_only, external_cluster, tmp_path):
    out = _interrupt_sweep(tmp_path, str(external_cluster), group=False)
    before = _snapshot(out)
    time.sleep(3)
    assert _snapshot(out) == before  # the workers write nothing more
    assert len(list(out.glob("points/*/scores/*.npz"))) < 6 * 10 * 3
    with distributed.Client(scheduler_file=str(external_cluster)) as client:
        assert not any(client.processing().values())


@pytest.mark.slow
def test_bench_scaling_smoke_on_cpu_workers(slow_only, tmp_path):
    from synthbos.benchmarks.bench_scaling import main as bench

    rows = bench(["--device", "cpu", "--counts", "1,2", "--pairs-per-gpu", "5", "--pixels", "96", "--rays", "20",
                  "--noise", "0,3", "--out", str(tmp_path)])
    assert [(r["units"], r["pairs"]) for r in rows] == [(1, 5), (2, 10)]
    assert all(r["identical_results"] and r["pairs_per_s"] > 0 for r in rows)
    assert "efficiency" in (tmp_path / "scaling.md").read_text()
    assert json.loads((tmp_path / "scaling.json").read_text())["rows"] == rows


def test_pipeline_tasks_on_a_local_cluster_give_the_plain_campaign(tmp_path):
    """Workers that run the pairs they take through the single-node pipeline (what a GPU worker does)
    write the files of a campaign run in one process, and leave no claims behind."""
    from dataclasses import replace

    from synthbos.benchmarks.campaign import run_campaign
    from synthbos.benchmarks.distributed import DaskRunner
    from synthbos.benchmarks.spec import FULL

    spec = replace(FULL, name="dask-pipeline", snapshots=(1, 4), pairs_per_snapshot=1, noise_percent=(3.0,),
                   config={"camera": {"pixels": [96, 96]}, "rays": {"per_dot": 20}})
    plain, dask = tmp_path / "plain", tmp_path / "dask"
    run_campaign(spec, plain, device="cpu", workers=1, progress=False, figures=False)
    with DaskRunner("local", device="cpu", workers=2, progress=False, pipeline=True) as runner:
        assert runner.pipeline
        run_campaign(spec, dask, device="cpu", scheduler=runner, progress=False, figures=False)
    assert (plain / "results.json").read_bytes() == (dask / "results.json").read_bytes()
    assert (plain / "floor.json").read_bytes() == (dask / "floor.json").read_bytes()
    # the pairs' density floors, kept in the campaign's folder (the pipeline tasks make them as the pairs appear)
    assert sorted(p.name for p in (dask / "floors").glob("*.npz")) == ["s1_p00.npz", "s4_p00.npz"]
    for path in sorted((plain / "scores").glob("*.npz")):
        with np.load(path) as a, np.load(dask / "scores" / path.name) as b:
            assert sorted(a.files) == sorted(b.files)
            assert all(a[k].tobytes() == b[k].tobytes() for k in a.files), path.name
    assert not list(dask.rglob(".claims-*"))


def _take_all(folder, n, out):
    from synthbos.benchmarks.drivers import FileClaims

    claims = FileClaims(folder, n)
    while claims.take() is not None:
        pass
    out.put((os.getpid(), claims.taken))


def test_file_claims_give_each_pair_to_one_process(tmp_path):
    """Four processes taking from one folder of claims: every task taken once, by one of them."""
    import multiprocessing
    import socket

    context = multiprocessing.get_context("spawn")
    out = context.SimpleQueue()
    procs = [context.Process(target=_take_all, args=(str(tmp_path), 200, out)) for _ in range(4)]
    for proc in procs:
        proc.start()
    taken = dict(out.get() for _ in procs)
    for proc in procs:
        proc.join(30)
    assert sorted(k for part in taken.values() for k in part) == list(range(200))
    assert all(part == sorted(part) for part in taken.values())
    host = socket.gethostname()
    for pid, part in taken.items():  # each claim names the process that took it
        assert all((tmp_path / str(k)).read_text() == f"{host} {pid}\n" for k in part)


def test_pairs_left_missing_by_a_round_are_run_again(tmp_path, monkeypatch):
    """A pipeline round that leaves pairs missing (a worker died with pairs it had taken) is followed by a
    round over those pairs only; pairs still missing after ``PIPELINE_ROUNDS`` rounds are one clear error."""
    from synthbos.benchmarks import distributed as dist

    from synthbos import SynthbosError

    renders = [({}, str(tmp_path / f"p{i}.h5"), "cuda:0") for i in range(3)]
    scores = [(r[1], "tracking", 1.0, (1, 2), r[1].replace(".h5", ".npz"), {}, "cuda:0") for r in renders]
    rounds = []

    def run_round(tasks, stack, bar):
        rounds.append([r[1] for r, _ in tasks])
        for r, items in tasks[1:] if len(rounds) == 1 else tasks:  # the first round loses its first pair
            for path in [r[1], *(s[4] for s in items)]:
                Path(path).touch()
        return 2 * len(tasks)

    runner = dist.DaskRunner("local", device="cuda:0", progress=False)
    monkeypatch.setattr(runner, "_run_round", run_round)
    assert runner.run_pairs(renders, scores) == 6 + 2
    assert rounds == [[r[1] for r in renders], [renders[0][1]]]

    Path(renders[0][1]).unlink()
    monkeypatch.setattr(runner, "_run_round", lambda tasks, stack, bar: rounds.append(len(tasks)) or 0)
    with pytest.raises(SynthbosError, match=f"1 pair\\(s\\) still missing after {dist.PIPELINE_ROUNDS} rounds"):
        runner.run_pairs(renders[:1], [])
    assert rounds[2:] == [1] * dist.PIPELINE_ROUNDS


def test_a_gpu_worker_keeps_its_host_processes_between_tasks():
    """``_kept_pool``: the same processes for the next pipeline task; new ones where the size changes."""
    from synthbos.benchmarks import distributed as dist

    assert dist._kept_pool(0, ()) is None
    first = dist._kept_pool(1, ())
    try:
        assert dist._kept_pool(1, ()) is first
        pid = first.submit(os.getpid).result()
        assert first.submit(os.getpid).result() == pid != os.getpid()
        second = dist._kept_pool(2, ())
        assert second is not first and dist._kept_pool(2, ()) is second
        with pytest.raises(RuntimeError):  # the first was shut down
            first.submit(os.getpid)
    finally:
        while dist._KEPT_POOL:
            dist._KEPT_POOL.pop()[1].shutdown(wait=True)


def test_the_bar_counts_pipeline_pairs_as_their_files_appear(tmp_path, monkeypatch):
    """Pipeline tasks end together, one a worker: the bar advances by each pair whose files are all there,
    while the tasks run, and once more when they have ended."""
    from synthbos.benchmarks import distributed as dist

    monkeypatch.setattr(dist, "PROGRESS_POLL_S", 0.05)
    outputs = [[str(tmp_path / f"p{i}.h5"), str(tmp_path / f"p{i}.npz")] for i in range(3)]
    counted = []

    class Bar:
        def update(self, n):
            counted.append(n)

    ended = threading.Event()
    watcher = threading.Thread(target=dist._watch_pairs, args=(outputs, Bar(), ended))
    watcher.start()
    for path in outputs[1]:
        Path(path).touch()
    deadline = time.monotonic() + 10
    while sum(counted) < 1 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert sum(counted) == 1  # the pair with both files, while the tasks run
    Path(outputs[0][0]).touch()  # half a pair: not finished
    for path in outputs[2]:
        Path(path).touch()
    ended.set()
    watcher.join(10)
    assert not watcher.is_alive() and sum(counted) == 2


class KillPipelineOnce(distributed.WorkerPlugin):
    """Kills, once, a worker that has taken pairs (its name in a claim file) when the campaign's first score
    file is there: it has not finished them (a pair is finished once its score files are all there). A
    worker that has taken none is left alone."""

    def __init__(self, marker, folder):
        self.marker, self.folder = str(marker), Path(folder)
        self.watching = False

    def transition(self, key, start, finish, **kwargs):
        if finish != "executing" or not str(key).startswith(f"{TASK_PREFIX}s-") or self.watching:
            return
        self.watching = True
        threading.Thread(target=self._kill_at_first_score, daemon=True).start()

    def _kill_at_first_score(self):
        import socket

        while not list(self.folder.glob("scores/*.npz")):
            time.sleep(0.002)
        me = f"{socket.gethostname()} {os.getpid()}"
        if not any(claim.read_text().strip() == me for claim in self.folder.glob("pairs/.claims-*/*")):
            return
        try:
            os.close(os.open(self.marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
        except FileExistsError:
            return
        Path(self.marker).write_text(json.dumps({"pid": os.getpid()}))
        os.kill(os.getpid(), signal.SIGKILL)


@pytest.mark.slow
def test_a_gpu_style_worker_killed_with_pairs_taken_loses_none(slow_only, external_cluster, tmp_path):
    """Pipeline tasks (what GPU workers run) on a joined cluster; one worker is killed once the first score
    file is there, with pairs it had taken: a later round runs them, and the campaign's files are those of
    a run in one process."""
    from dataclasses import replace

    import psutil
    from synthbos.benchmarks.campaign import run_campaign
    from synthbos.benchmarks.distributed import DaskRunner
    from synthbos.benchmarks.spec import FULL

    spec = replace(FULL, name="killed-pipeline", pairs_per_snapshot=1, noise_percent=(3.0,),
                   config={"camera": {"pixels": [96, 96]}, "rays": {"per_dot": 20}})
    plain, dask, marker = tmp_path / "plain", tmp_path / "dask", tmp_path / "killed.json"
    run_campaign(spec, plain, device="cpu", workers=1, progress=False, figures=False)
    rounds = []
    with distributed.Client(scheduler_file=str(external_cluster)) as client:
        with _worker_plugin(client, KillPipelineOnce(marker, dask), "kill-pipeline-once"), \
                DaskRunner(str(external_cluster), progress=False, pipeline=True) as runner:
            one_round = runner._run_round
            runner._run_round = lambda tasks, *args: rounds.append(len(tasks)) or one_round(tasks, *args)
            run_campaign(spec, dask, device="cpu", scheduler=runner, progress=False, figures=False)
        client.wait_for_workers(2, timeout=60)  # the nanny has started the killed one again
    assert not psutil.pid_exists(json.loads(marker.read_text())["pid"])
    # every pair in the first round; the pairs the killed worker had taken and not finished in the second (a
    # worker takes the pairs its renders ahead need at its start: here perhaps all five)
    assert len(rounds) == 2 and rounds[0] == 5 and 1 <= rounds[1] <= 5, rounds
    assert (plain / "results.json").read_bytes() == (dask / "results.json").read_bytes()
    for path in sorted((plain / "scores").glob("*.npz")):
        with np.load(path) as a, np.load(dask / "scores" / path.name) as b:
            assert all(a[k].tobytes() == b[k].tobytes() for k in a.files), path.name
    assert sorted(p.name for p in (dask / "scores").glob("*.npz")) == sorted(
        p.name for p in (plain / "scores").glob("*.npz"))
    assert not list(dask.rglob(".claims-*")) and not list(dask.rglob(".*.tmp"))
