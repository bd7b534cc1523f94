"""The reliability corpus (issue 14): bad inputs of every kind, generated in temporary folders. Each must end in a
clean one-line error naming what is wrong, a non-zero exit, and no partial output."""

from pathlib import Path

from warpsense.cli import main


def files_under(folder: Path) -> set[Path]:
    return {path for path in folder.rglob("*")} if folder.exists() else set()


def assert_clean_failure(capsys, argv: list[str], names: tuple[str, ...], watched: Path | None = None) -> None:
    """``warpsense argv`` fails with exit != 0 and one stderr line (no traceback) that contains every string of
    ``names``; nothing new appears under ``watched``."""
    before = files_under(watched) if watched is not None else set()
    try:
        code = main(argv)
    except SystemExit as exit_:  # argparse's own usage errors
        code = exit_.code
    error = capsys.readouterr().err.strip()
    assert code not in (0, None), f"accepted: {argv}"
    assert error and "\n" not in error and "Traceback" not in error, error
    for name in names:
        assert name in error, f"{name!r} not named in: {error}"
    if watched is not None:
        assert files_under(watched) == before, f"partial output: {sorted(files_under(watched) - before)}"
