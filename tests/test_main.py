"""``python -m synthbos``: a command that returns leaves without the interpreter's teardown, with its exit
status and all of its output."""

import subprocess
import sys


def run(*args):
    return subprocess.run([sys.executable, "-m", "synthbos", *args], capture_output=True, text=True, check=False)


def test_a_command_leaves_with_its_status_and_its_whole_output():
    done = run("methods")
    assert done.returncode == 0
    assert "correlation" in done.stdout and "tracking-cc" in done.stdout and done.stdout.endswith("\n")
    usage = run("paper", "--nonsense")
    assert usage.returncode == 2 and usage.stderr.strip().endswith("unrecognized arguments: --nonsense")
    helped = run("--version")
    assert helped.returncode == 0 and helped.stdout.startswith("synthbos")


def test_the_last_exit_handler_does_nothing_before_a_command_returned():
    from synthbos import __main__ as entry

    assert entry._STATUS == []
    entry._leave()  # returns: the interpreter's own exit goes on (here: pytest's)
