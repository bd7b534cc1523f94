"""Writing output files: a temporary beside the target, then one atomic rename, with the permissions the user's umask
gives a new file (safetensors and mkstemp create 0600 files, which other users of a shared run folder cannot read)."""

from __future__ import annotations

import contextlib
import json
import os
import platform
import subprocess
from collections.abc import Iterator
from pathlib import Path


class Folder:
    """A folder that an owner class names the files of (`warpsense.train.run_dir.RunDir`,
    `warpsense.study.study_dir.StudyDir`): built from its path, printed and passed to ``open``/``os`` as that path."""

    def __init__(self, path: str | Path):
        self.path = Path(path)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.path)!r})"

    def __str__(self) -> str:
        return str(self.path)

    def __fspath__(self) -> str:
        return str(self.path)


def located(path: str | Path) -> str:
    """``path`` as an error names a file it looked for: a relative path with the absolute one it resolved to from the
    working directory ("classes.toml (/home/me/run/classes.toml)"), where a path in a config or on the command line
    is read from; an absolute path as it is."""
    path = Path(path)
    return str(path) if path.is_absolute() else f"{path} ({Path.cwd() / path})"


def publish(temporary: str | Path, target: str | Path) -> None:
    """Give ``temporary`` the default mode for a new file (0666 minus the umask) and rename it onto ``target``."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(temporary, 0o666 & ~umask)
    os.replace(temporary, target)


@contextlib.contextmanager
def atomic_write(target: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``target`` to write to; when the block ends normally it is `publish`ed onto
    ``target``, and on any error (or a kill before the rename) ``target`` keeps its old content and the temporary is
    removed."""
    target = Path(target)
    temporary = target.with_name(target.name + ".tmp")
    try:
        yield temporary
        publish(temporary, target)
    finally:
        temporary.unlink(missing_ok=True)


def write_json(path: str | Path, payload, indent: int = 2, sort_keys: bool = False) -> None:
    """Write ``payload`` as JSON at ``path`` atomically (`atomic_write`)."""
    with atomic_write(path) as temporary:
        temporary.write_text(json.dumps(payload, indent=indent, sort_keys=sort_keys) + "\n")


def check_output_file(path: str | Path | None, what: str) -> None:
    """Refuse, before any long work, an output file path that cannot be written: a folder, a missing or
    non-writable parent folder. ValueError naming the option and path."""
    if not path:
        return
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
        raise ValueError(f"{what} {path}: is a folder, expected a file path")
    if not parent.is_dir():
        raise ValueError(f"{what} {path}: folder {parent} does not exist")
    if not os.access(parent, os.W_OK):
        raise ValueError(f"{what} {path}: folder {parent} is not writable")


def check_plot_file(path: str | Path | None, what: str) -> None:
    """`check_output_file` for a figure, whose suffix names its format: one matplotlib writes (png, pdf, svg, ...),
    refused before any work otherwise (matplotlib would fail only once the figure is drawn)."""
    check_output_file(path, what)
    if not path:
        return
    from matplotlib.backend_bases import FigureCanvasBase

    formats = FigureCanvasBase.get_supported_filetypes()
    if Path(path).suffix.lower().lstrip(".") not in formats:  # plot_format's PNG default is for the Python API
        raise ValueError(f"{what} {path}: the file's suffix names the image format, one of "
                         f"{', '.join('.' + name for name in sorted(formats))}")


def plot_format(path: str | Path) -> str:
    """The image format a figure path's suffix names (`check_plot_file` checked it; PNG without a suffix), for a
    save to another (temporary) name."""
    return Path(path).suffix.lower().lstrip(".") or "png"


def check_output_folder(path: str | Path, what: str) -> None:
    """Refuse an output folder named by empty text (an unset shell variable: Path("") is the current folder), a
    file, or under a non-writable folder (it may not exist yet)."""
    if not str(path):
        raise ValueError(f"{what} is empty: name a folder ('.' for the current one)")
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ValueError(f"{what} {path}: is a file, expected a folder")
    existing = path
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir() or not os.access(existing, os.W_OK):
        raise ValueError(f"{what} {path}: {existing} is not a writable folder")


def _git(*arguments: str, cwd: Path) -> str | None:
    """git's stdout in ``cwd``, or None when git is missing, fails or times out."""
    try:
        result = subprocess.run(["git", *arguments], cwd=cwd, capture_output=True, text=True, timeout=5)
    except (OSError, subprocess.SubprocessError):
        return None
    # outside a repository git prints its argument back on stdout: only trust a successful answer
    return result.stdout if result.returncode == 0 else None


def source_state(source: Path) -> tuple[str | None, bool | None]:
    """(commit, dirty) of the git checkout holding ``source``: the HEAD commit, and whether tracked files differ
    from it (a run from an edited tree is not that commit's run); (None, None) outside a checkout."""
    commit = (_git("rev-parse", "HEAD", cwd=source) or "").strip() or None
    if commit is None:
        return None, None
    changes = _git("status", "--porcelain", "--untracked-files=no", cwd=source)
    return commit, None if changes is None else bool(changes.strip())


def environment() -> dict:
    """What produced a run or checkpoint: warpsense, torch, Warp and Python versions, the device, and the git
    commit of the source tree with whether its tracked files were edited (None outside a git checkout)."""
    import torch
    import warp

    from warpsense import __version__

    commit, dirty = source_state(Path(__file__).resolve().parent)
    return {"warpsense": __version__, "torch": torch.__version__, "warp": warp.config.version,
            "python": platform.python_version(), "git_commit": commit, "git_dirty": dirty,
            "cuda_device": torch.cuda.get_device_name() if torch.cuda.is_available() else None}
