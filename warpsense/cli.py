"""The `warpsense` command line: the top-level parser over the commands' own (`warpsense.commands`), and the
dispatch to the parsed command with its errors as one line each."""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
from collections.abc import Iterator

from warpsense import __version__
from warpsense.commands import bench, calibrate, convert, lens, predict, simulate, study, train
from warpsense.commands import eval as evaluate

COMMANDS = {"train": train, "eval": evaluate, "bench": bench, "convert": convert, "predict": predict, "study": study,
            "lens": lens, "simulate": simulate, "calibrate": calibrate}
"""Each command's module, in the order `warpsense --help` lists them: its ``register(commands, name)`` adds its
parser, its ``run(args)`` runs the parsed command and returns the exit code."""


def build_parser() -> argparse.ArgumentParser:
    """The `warpsense` parser: --version, and each command of `COMMANDS` with the arguments it registers."""
    parser = argparse.ArgumentParser(prog="warpsense", description="Camera co-design for driving perception: a "
                                     "differentiable camera (lens, exposure, colour filters, noise, ADC) in NVIDIA "
                                     "Warp, trained with a segmentation network; compare cameras with `warpsense "
                                     "study`.")
    parser.add_argument("--version", action="version", version=f"warpsense {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module in COMMANDS.items():
        module.register(commands, name)
    return parser


CPU_THREAD_DEFAULTS = {"OMP_WAIT_POLICY": "PASSIVE"}
"""Environment defaults for torch's OpenMP runtime that `main` sets before torch loads, where the caller has not set
them: an OpenMP thread waiting for work sleeps instead of spinning. libgomp's default spins at every barrier, which
takes the cores from the threads with work whenever another job shares them, and training slows several-fold beside
another CPU job (docs/benchmarks.md, CPU; tools/bench_threads.py). OMP_WAIT_POLICY=ACTIVE in the environment keeps
spinning on a machine of one's own."""


def _cpu_thread_defaults() -> None:
    """Set `CPU_THREAD_DEFAULTS` where the environment does not; child processes (a study's workers, torchrun's
    ranks) inherit them."""
    for key, value in CPU_THREAD_DEFAULTS.items():
        os.environ.setdefault(key, value)


@contextlib.contextmanager
def _terminate_as_interrupt() -> Iterator[list[int]]:
    """While the block runs, SIGTERM (what `kill`, torchrun, or a cluster scheduler before its SIGKILL sends) raises
    KeyboardInterrupt, as Ctrl-C does: Python's default ended the process on the spot, so a training killed so left
    a run folder without a checkpoint (its first epoch), a half-written checkpoint's .tmp and its lock, and said
    nothing. Now training keeps its last epoch's checkpoint and says how to resume, a study stops its workers, and
    each command cleans up as after Ctrl-C. A second SIGTERM ends the process at once. Yields a list that holds the
    signal once one came. SIGTERM is left alone where it is not at its default (a parent made it ignored, a caller
    handles it) or off the main thread."""
    received: list[int] = []

    def interrupt(signum, frame):
        received.append(signum)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        raise KeyboardInterrupt

    previous = None
    with contextlib.suppress(ValueError):  # signal.signal works on the main thread only
        if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
            previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield received
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def main(argv: list[str] | None = None) -> int:
    """Parse ``argv`` (default: the process's arguments) and run the command; returns its exit code, 2 (with a
    one-line error on stderr) where it failed on bad input, 130 after Ctrl-C, 2 with the help when no command is
    given, and 141 without a word where the reader of stdout went away (`quiet_broken_pipe`)."""
    with quiet_broken_pipe() as status:
        status.append(_main(argv))
    return status[-1]


@contextlib.contextmanager
def quiet_broken_pipe() -> Iterator[list[int]]:
    """Where stdout's reader closes early (``warpsense train --print-config | head``, ``less`` quit), end quietly
    with 141 (128 + SIGPIPE, what the shell reports for git or cat killed by the signal): Python ignores SIGPIPE, so
    the write raised BrokenPipeError, which the command's bad-input handler printed as "error: [Errno 32] Broken
    pipe" with exit 2, or, where the output still sat in stdout's buffer, the interpreter printed "Exception ignored
    ... BrokenPipeError" at exit. stdout is flushed inside the block (argparse's --help exits with its text still
    buffered), then pointed at /dev/null so that nothing is written to the closed pipe at exit. Yields a list the
    block appends its exit code to; on a broken pipe 141 is appended."""
    status: list[int] = []
    try:
        try:
            yield status
        finally:  # --help and --version leave by SystemExit with their text in the buffer
            sys.stdout.flush()
    except BrokenPipeError:
        with contextlib.suppress(OSError, ValueError):  # no stdout descriptor (an embedding host): nothing to point
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            os.close(devnull)
        status.append(128 + BROKEN_PIPE_SIGNAL)


BROKEN_PIPE_SIGNAL = 13
"""SIGPIPE's number (POSIX); `signal.SIGPIPE` is missing on Windows."""


def _main(argv: list[str] | None) -> int:
    _cpu_thread_defaults()  # before anything imports torch, which loads the OpenMP runtime that reads them once
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    with _terminate_as_interrupt() as terminated:
        code = _run(args)
    return 128 + signal.SIGTERM if terminated and code == 130 else code  # as the shell reports a SIGTERM


def _run(args: argparse.Namespace) -> int:
    """Run the parsed command; its exit code, with bad input and Ctrl-C as one line each."""
    from warpsense.config import ConfigError
    from warpsense.data.datasets import DatasetError
    from warpsense.errors import first_line, worker_message
    from warpsense.optics.lens import LensFileError
    from warpsense.study.plan import PlanError

    try:
        return COMMANDS[args.command].run(args)
    except BrokenPipeError:  # stdout's reader went away: `main` ends quietly
        raise
    except (ConfigError, DatasetError, LensFileError, PlanError, OSError, KeyError, ValueError) as error:
        message = error.args[0] if isinstance(error, KeyError) and error.args else error
        # a bad file read by a DataLoader worker (data.num_workers > 0) comes back with the worker's traceback
        print(f"warpsense {args.command}: error: {worker_message(str(message))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # train and study say how to resume themselves; the others stop here in one line
        print(f"warpsense {args.command}: interrupted", file=sys.stderr)
        return 130
    except RuntimeError as error:
        if not out_of_memory(error):
            raise
        print(f"warpsense {args.command}: error: out of memory ({first_line(error)}): lower the batch size or the "
              "image size (data.batch_size, data.crop_height / crop_width; eval --batch-size, --latency-size)",
              file=sys.stderr)
        return 2


def out_of_memory(error: BaseException) -> bool:
    """Whether ``error`` is torch's failure to allocate memory: torch.OutOfMemoryError on a GPU, a RuntimeError
    from the CPU allocator ("DefaultCPUAllocator: can't allocate memory")."""
    return type(error).__name__ == "OutOfMemoryError" or "can't allocate memory" in str(error)


if __name__ == "__main__":
    sys.exit(main())
