"""bench_cold times a command cold then warm, each repeat with a kernel cache of its own that starts empty."""

import doctest
import hashlib
import sys

import pytest
from synthbos.benchmarks import bench_cold

from synthbos import SynthbosError

# Writes into results.csv whether the kernel cache it was given was empty, then leaves a file in it.
_SCRIPT = """
import os, sys
cache = os.environ["WARP_CACHE_PATH"]
state = "filled" if os.listdir(cache) else "empty"
open(os.path.join(cache, "kernel.o"), "w").write("x")
open(os.path.join(sys.argv[1], "results.csv"), "w").write(state)
"""


def _md5(text):
    return hashlib.md5(text.encode()).hexdigest()


def test_each_repeat_runs_cold_on_an_empty_cache_then_warm_on_the_same(tmp_path):
    rows = bench_cold.cold_and_warm([sys.executable, "-c", _SCRIPT, "{out}"], repeats=2, workdir=tmp_path)
    assert [(r["repeat"], r["run"]) for r in rows] == [(0, "cold"), (0, "warm"), (1, "cold"), (1, "warm")]
    assert [r["results_md5"] for r in rows] == [_md5("empty"), _md5("filled")] * 2
    assert rows[0]["cache"] == rows[1]["cache"] != rows[2]["cache"] == rows[3]["cache"]
    assert all(r["wall_s"] > 0 and r["load_before"] >= 0 for r in rows)
    report = bench_cold._report(rows)
    assert "results.csv identical in every run: NO" in report  # the script's results differ cold and warm
    ratio = rows[0]["wall_s"] / rows[1]["wall_s"]
    assert f"first run (shipped CPU kernels) / warm run: {ratio:.2f}, " in report
    assert "every kernel compiled" not in report


# Writes into results.csv whether it was asked to copy no shipped kernel.
_SWITCH = """
import os, sys
open(os.path.join(sys.argv[1], "results.csv"), "w").write(os.environ.get("SYNTHBOS_SHIPPED_KERNELS", "unset"))
"""


def test_the_compiled_run_copies_no_shipped_kernel_and_has_a_cache_of_its_own(tmp_path):
    rows = bench_cold.cold_and_warm([sys.executable, "-c", _SWITCH, "{out}"], repeats=1, workdir=tmp_path,
                                    compiled=True)
    assert [r["run"] for r in rows] == ["cold", "warm", "compiled"]
    assert [r["results_md5"] for r in rows] == [_md5("unset"), _md5("unset"), _md5("0")]
    assert rows[0]["cache"] == rows[1]["cache"] != rows[2]["cache"]
    ratio = rows[2]["wall_s"] / rows[1]["wall_s"]
    assert f"first run, every kernel compiled / warm run: {ratio:.2f}" in bench_cold._report(rows)


def test_a_failing_command_is_one_line_with_its_last_error(tmp_path):
    script = "import sys; sys.stderr.write('first\\nthe real reason\\n'); sys.exit(3)"
    with pytest.raises(SynthbosError, match="exit status 3: the real reason"):
        bench_cold.time_run([sys.executable, "-c", script], cache=tmp_path, out=tmp_path)


def test_the_example_runs():
    fn = bench_cold.cold_and_warm
    tests = [t for t in doctest.DocTestFinder().find(fn, "cold_and_warm", globs={"cold_and_warm": fn}) if t.examples]
    assert tests
    for test in tests:
        assert doctest.DocTestRunner().run(test).failed == 0
