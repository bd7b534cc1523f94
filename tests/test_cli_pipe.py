"""A command's output into a reader that has gone away (`| head`, `less` quit): the command ends quietly, as git
and pip do (warpsense/cli.py, `quiet_broken_pipe`)."""

import os
import subprocess
import sys

import pytest


def _into_closed_pipe(*arguments: str) -> subprocess.CompletedProcess:
    """Run `python -m warpsense ARGUMENTS` with stdout a pipe whose read end is closed before it starts (so every
    write fails with EPIPE, whatever the timing)."""
    read, write = os.pipe()
    os.close(read)
    try:
        return subprocess.run([sys.executable, "-m", "warpsense", *arguments], stdout=write, stderr=subprocess.PIPE,
                              text=True, timeout=300)
    finally:
        os.close(write)


@pytest.mark.parametrize("arguments", [["train", "--print-config"], ["study", "run", "smoke", "--out", "{tmp}",
                                                                     "--plan-only"]])
def test_output_into_a_closed_pipe_ends_quietly_with_the_shells_sigpipe_status(tmp_path, arguments):
    # before: "warpsense train: error: [Errno 32] Broken pipe" on stderr and exit 2, as for bad input
    result = _into_closed_pipe(*(a.format(tmp=tmp_path / "study") for a in arguments))
    assert result.stderr == "" and result.returncode == 141  # 128 + SIGPIPE, as the shell reports `git log | true`


def test_help_into_a_closed_pipe_ends_quietly():
    result = _into_closed_pipe("--help")
    assert result.stderr == "" and result.returncode in (0, 141)
