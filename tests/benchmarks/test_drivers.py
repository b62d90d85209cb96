"""Several processes driving one device through a campaign's pipeline (``benchmarks.drivers``,
``scheduling.run_pipeline(drivers=...)``): every pair taken once, the same files whatever the count,
a helper's failure reported in one line."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from dataclasses import replace

import pytest
from synthbos.benchmarks import drivers as drv
from synthbos.benchmarks.campaign import run_campaign
from synthbos.benchmarks.cli import main
from synthbos.benchmarks.spec import REGRESS

from synthbos import SynthbosError


def _take_all(claims, driver, out):
    """A process that takes tasks until none is left, and reports them."""
    mine = []
    while (k := claims.take(driver)) is not None:
        mine.append(k)
        time.sleep(0.001)
    out.put((driver, mine))


def _fail(claims, number, campaign_pid):
    claims.fail("pair s0_p03.h5: the render failed")
    sys.exit(1)


def _killed(claims, number, campaign_pid):
    os.kill(os.getpid(), signal.SIGKILL)


def test_claims_give_every_task_to_one_process():
    context = drv.driver_context()
    claims = drv.Claims(200, context)
    out = context.SimpleQueue()
    procs = [context.Process(target=_take_all, args=(claims, d, out)) for d in range(3)]
    for p in procs:
        p.start()
    got = dict(out.get() for _ in procs)
    for p in procs:
        p.join(30)
    taken = [k for d in got for k in got[d]]
    assert sorted(taken) == list(range(200))  # each task once
    assert claims.counts(3) == [len(got[d]) for d in range(3)]
    assert claims.take(0) is None


@pytest.mark.parametrize(("target", "message"), [
    (_fail, r"^pair s0_p03.h5: the render failed$"),  # a helper's failure, in one line
    (_killed, r"synthbos-driver-1.*exit status -9.*run the campaign again"),  # a killed helper, named
])
def test_a_helper_that_fails_or_dies_is_reported_in_one_line(target, message):
    context = drv.driver_context()
    claims = drv.Claims(4, context)
    procs = drv.start_drivers(1, target, (claims,), context)
    with pytest.raises(SynthbosError, match=message):
        drv.join_drivers(procs, claims)


def test_two_drivers_write_the_same_files(tmp_path, monkeypatch):
    """A CPU pipeline (as a GPU campaign runs) with a helper: every score file, the results and the floor
    table are the same bytes as with one process, and the helper took pairs (this process waits, after its
    first pair, until the helper has taken one, so both take part however fast the machine is)."""
    spec = replace(REGRESS, snapshots=(0, 2, 4), pairs_per_snapshot=2,
                   config={"camera": {"pixels": [96, 96]}, "rays": {"per_dot": 20}})
    take = drv.Claims.take

    def patient(self, driver=0):
        k = take(self, driver)
        deadline = time.monotonic() + 120
        while k is not None and k > 0 and self.counts(2)[1] == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        return k

    logs = {}
    for name, n in (("one", 1), ("two", 2)):
        if n == 2:
            monkeypatch.setattr(drv.Claims, "take", patient)
        logs[name] = []
        run_campaign(spec, tmp_path / name, device="cpu", pipeline=True, workers=3, drivers=n, progress=False,
                     drivers_log=logs[name])
    assert logs["one"] == [6]
    assert len(logs["two"]) == 2 and sum(logs["two"]) == 6 and min(logs["two"]) >= 1, logs
    one, two = tmp_path / "one", tmp_path / "two"
    names = sorted(p.name for p in (one / "scores").glob("*.npz"))
    assert len(names) == 6 * 2 * 3
    for name in names:
        assert (one / "scores" / name).read_bytes() == (two / "scores" / name).read_bytes(), name
    for table in ("results.csv", "floor.csv"):
        assert (one / table).read_bytes() == (two / table).read_bytes(), table
    assert sorted(p.name for p in (two / "floors").iterdir()) == sorted(p.name for p in (one / "floors").iterdir())


@pytest.mark.parametrize(("value", "message"), [("0", "must be 1 or more processes, got 0"),
                                              ("two", "must be a whole number of processes, got 'two'")])
def test_a_bad_driver_count_is_a_usage_error(tmp_path, capsys, value, message):
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exit_:
        main(["paper", "--quick", "--device", "cpu", "--drivers", value, "-o", str(out)])
    assert exit_.value.code == 2 and f"--drivers: {message}" in capsys.readouterr().err
    assert not out.exists()


def test_run_campaign_refuses_a_bad_driver_count(tmp_path):
    with pytest.raises(SynthbosError, match="--drivers must be a whole number"):
        run_campaign(REGRESS, tmp_path / "x", device="cpu", drivers=0)
    assert not (tmp_path / "x").exists()


def _interrupted(tmp_path, delay, out):
    """``paper --quick`` on the CPU pipeline with two drivers, and a terminal's Ctrl-C (the whole process group)
    after ``delay`` seconds; returns the command line. Asserts one line, status 130, no process of the run's
    session left and no temporary file."""
    argv = [sys.executable, "-m", "synthbos", "paper", "--quick", "--device", "cpu", "--stack", "2", "--drivers", "2",
            "-q", "-o", str(out)]
    proc = subprocess.Popen(argv, cwd=tmp_path, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)
    time.sleep(delay)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("Warp")]
    assert proc.returncode == 130 and lines == ["synthbos: interrupted; finished items are kept, re-run to resume"], err
    deadline = time.monotonic() + 15  # (the processes of the session end as their parents do: seconds)
    while (left := subprocess.run(["pgrep", "-s", str(proc.pid)], capture_output=True, text=True).stdout.split()) \
            and time.monotonic() < deadline:
        time.sleep(0.5)
    assert left == [], left  # no helper, fork server or host process of the session
    if out.exists():
        assert not list(out.rglob(".*.tmp"))
    return argv


def test_ctrl_c_while_the_helper_starts_prints_one_line(tmp_path):
    """A Ctrl-C while the fork server imports the helper's modules: one line (the server, started with
    SIGINT ignored, prints no traceback of its own; the resource tracker no warning)."""
    _interrupted(tmp_path, 4.0, tmp_path / "camp")


@pytest.mark.slow
def test_ctrl_c_with_helpers_then_a_run_again_gives_the_same_results(tmp_path, slow_only):
    out = tmp_path / "camp"
    argv = _interrupted(tmp_path, 12.0, out)
    assert subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, timeout=600).returncode == 0
    assert main(["paper", "--quick", "--device", "cpu", "-q", "-o", str(tmp_path / "one")]) == 0
    assert (out / "results.csv").read_bytes() == (tmp_path / "one" / "results.csv").read_bytes()
