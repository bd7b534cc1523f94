"""warpsense.files: the commit and edited-or-not state a run's environment.json records (source_state); output folders
checked before anything is written."""

import subprocess

import pytest

from warpsense.files import check_output_folder, environment, source_state


def _git(repo, *arguments):
    return subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *arguments], cwd=repo, check=True,
                          capture_output=True, text=True).stdout.strip()


def test_commit_and_edited_tracked_files(tmp_path):
    assert source_state(tmp_path) == (None, None)  # not a checkout
    _git(tmp_path, "init", "-q")
    (tmp_path / "a.py").write_text("x = 1\n")
    _git(tmp_path, "add", "a.py")
    _git(tmp_path, "commit", "-q", "-m", "one")
    head = _git(tmp_path, "rev-parse", "HEAD")
    assert source_state(tmp_path) == (head, False)
    (tmp_path / "new.py").write_text("")  # untracked files leave the commit's code as it was
    assert source_state(tmp_path) == (head, False)
    (tmp_path / "a.py").write_text("x = 2\n")
    assert source_state(tmp_path) == (head, True)
    (tmp_path / "sub").mkdir()
    assert source_state(tmp_path / "sub") == (head, True)  # from inside the tree


def test_environment_records_both():
    record = environment()
    assert (record["git_commit"] is None) == (record["git_dirty"] is None)


def test_an_empty_output_folder_is_refused_naming_the_option():
    """`--out ""` (an unset shell variable) wrote into the current folder and said "into " with no folder."""
    with pytest.raises(ValueError, match=r"^--out is empty: name a folder \('\.' for the current one\)$"):
        check_output_folder("", "--out")
    check_output_folder(".", "--out")  # the current folder, named, is fine
