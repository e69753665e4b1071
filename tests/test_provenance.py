"""Results files name the commit they ran at; benchmark output alone does not make it '+changes'."""

import shutil
import subprocess

import pytest

from experiments.provenance import git_commit, provenance


def _git(repo, *args):
  subprocess.run(["git", *args], cwd=repo, check=True, capture_output=True)


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git")
def test_git_commit_ignores_results_files_but_not_code(tmp_path):
  _git(tmp_path, "init", "-q")
  (tmp_path / "benchmarks" / "results").mkdir(parents=True)
  (tmp_path / "code.py").write_text("x = 1\n")
  (tmp_path / "benchmarks" / "results" / "a.md").write_text("old\n")
  _git(tmp_path, "add", ".")
  _git(tmp_path, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "init")
  head = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=tmp_path, check=True,
                        capture_output=True, text=True).stdout.strip()
  assert git_commit(tmp_path) == head
  (tmp_path / "benchmarks" / "results" / "a.md").write_text("new\n")   # a benchmark wrote this
  assert git_commit(tmp_path) == head
  (tmp_path / "code.py").write_text("x = 2\n")                          # the code differs
  assert git_commit(tmp_path).startswith(head + " +changes")


def test_provenance_names_command_date_machine_and_commit():
  lines = provenance("python -m benchmarks.something --flag")
  text = "\n".join(lines)
  assert lines[0] == "Produced by `python -m benchmarks.something --flag`."
  for needle in ("- Date: ", "- Machine: ", "- Commit: ", "- Load average"):
    assert needle in text, needle
