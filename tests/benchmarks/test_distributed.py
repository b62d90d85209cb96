"""Campaigns on a Dask cluster give the files of a run in one process, byte for byte, and survive a dead worker.

Every test runs the same tiny sweep (two noise levels, each point a campaign of two 96 x 96 pairs and
all three methods) and compares its folder with the same sweep run in this process: the tables byte
for byte, every score array and every pair dataset bit for bit. (Pair files store the render's wall
time and score files are zip archives stamped with their write time, so those two kinds of file are
compared by content, not as raw bytes.)
"""

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
                assert da[k].dtype == db[k].dtype and da[k].tobytes() == db[k].tobytes(), (rel, k)
        else:  # campaign.json, results.csv, results.json, sweep_params.json
            assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel


def test_pair_tasks_group_items_by_pair():
    renders = [({"c": 1}, "/f/pairs/s1_p00.h5", "cpu")]
    scores = [(f"/f/pairs/s{s}_p00.h5", m, 0.0, (1, 2), f"/f/scores/s{s}_{m}.npz", {}) for s in (1, 2)
              for m in ("a", "b")]
    tasks = _pair_tasks(renders, scores)
    assert [(r is not None, [s[1] for s in items]) for r, items in tasks] == [(True, ["a", "b"]), (False, ["a", "b"])]


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


@pytest.fixture
def external_cluster(tmp_path):
    """A scheduler and two single-threaded workers, each its own process on 127.0.0.1 (no nannies)."""
    sched_file = tmp_path / "scheduler.json"
    log = open(tmp_path / "cluster.log", "w")
    procs = [_start(["distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                     "--scheduler-file", str(sched_file)], log)]
    workers = [_start(["distributed.cli.dask_worker", "--scheduler-file", str(sched_file), "--host", "127.0.0.1",
                       "--nthreads", "1", "--no-nanny", "--no-dashboard", "--name", f"w{i}",
                       "--local-directory", str(tmp_path / f"w{i}")], log) for i in range(2)]
    procs += workers
    try:
        deadline = time.monotonic() + 60
        while not sched_file.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        with distributed.Client(scheduler_file=str(sched_file), timeout="60s") as client:
            client.wait_for_workers(2, timeout=60)
        yield sched_file, workers
    finally:  # the workers are idle by now: no need for a graceful end
        for p in workers:
            p.kill()
        procs[0].terminate()
        for p in procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        log.close()


def test_scheduler_and_workers_as_separate_processes_match_plain_run(plain, external_cluster, tmp_path):
    sched_file, _ = external_cluster
    address = json.loads(sched_file.read_text())["address"]
    assert address.startswith("tcp://127.0.0.1:")
    out = tmp_path / "sweep"
    _sweep(out, "--scheduler", address)
    assert_same_results(plain, out)


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
    import cloudpickle

    sched_file, workers = external_cluster
    out = tmp_path / "sweep"
    marker = tmp_path / "killed.json"
    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the workers cannot import this test module
    try:
        with distributed.Client(scheduler_file=str(sched_file)) as client:
            client.register_plugin(KillOnce(marker, out))
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
    _sweep(out, "--scheduler", str(sched_file))
    killed = json.loads(marker.read_text())
    assert [w.poll() for w in workers].count(-signal.SIGKILL) == 1
    assert killed["pid"] in [w.pid for w in workers]
    # The other worker finished the pair task in flight, and rewrote none of the files already there.
    for path in killed["done"]:
        assert Path(path).stat().st_mtime_ns <= marker.stat().st_mtime_ns
    assert_same_results(plain, out)
