"""``benchmarks/README.md`` is generated from the results files' headers; ``--touched`` lists the files
a change can move."""

import subprocess

import pytest

from benchmarks import index


def test_the_committed_index_is_what_the_results_files_say():
  assert index.INDEX.read_text() == index.render(), (
      "benchmarks/README.md is out of date: run python -m benchmarks.index")


def test_every_results_file_names_its_command_date_machine_and_commit():
  for e in index.entries():
    assert e.command.startswith("python -m "), e
    assert e.date[:4].isdigit() and e.machine != "?" and e.commit != "?", e


def test_a_header_is_read_as_written_and_a_file_without_a_command_is_refused(tmp_path):
  (tmp_path / "thing.md").write_text(
      "# A thing\n\nProduced by `python -m benchmarks.thing --fast`.\n\n- Date: 2026-01-02T03:04:05+00:00\n"
      "- Machine: Some CPU; 2 usable cores\n- Commit: 0123456789ab +changes\n")
  (tmp_path / "thing.json").write_text("{}")
  (tmp_path / "plain.md").write_text("# Plain\n\nProduced by `python -m p`.\n\n- Date: 2026-01-01\n"
                                     "- Machine: M\n- Commit: 1\n")
  (tmp_path / "thing_more.md").write_text("# More\n\nProduced by `python -m x` on 2026-02-03 (5 s).\n"
                                          "- CPU: Other CPU; 4 cores\n")
  (tmp_path / "thing_more.png").write_bytes(b"")
  plain, a, b = index.entries(tmp_path)
  assert a == index.Entry("thing", "A thing", "python -m benchmarks.thing --fast", "2026-01-02T03:04:05+00:00",
                          "Some CPU", "0123456789ab +changes")
  assert (b.date, b.machine, b.commit) == ("2026-02-03", "Other CPU", "?")
  assert index.companions(tmp_path, "thing") == ["thing.json"]       # thing_more.png is the other's
  assert index.companions(tmp_path, "thing_more") == ["thing_more.png"]
  (tmp_path / "bad.md").write_text("# No command\n")
  with pytest.raises(ValueError, match="Produced by"):
    index.entries(tmp_path)


def test_results_are_read_from_benchmarks_and_each_studys_folder_and_a_name_is_one_file(tmp_path, monkeypatch):
  """Performance results in ``benchmarks/results``, each study's in its own ``results/``; the index
  links each where it lies, and a name in two folders is refused."""
  bench, study = tmp_path / "benchmarks" / "results", tmp_path / "experiments" / "studies" / "s" / "results"
  for folder in (bench, study, tmp_path / "experiments" / "studies" / "t"):      # t keeps no results
    folder.mkdir(parents=True)
  assert index.results_folders(tmp_path) == [bench, study]
  head = "# {0}\n\nProduced by `python -m {0}`.\n\n- Date: 2026-01-02\n- Machine: M\n- Commit: 1\n"
  (bench / "speed.md").write_text(head.format("speed"))
  (study / "answer.md").write_text(head.format("answer"))
  (study / "answer.png").write_bytes(b"")
  monkeypatch.setattr(index, "results_folders", lambda: [bench, study])
  monkeypatch.setattr(index, "HERE", tmp_path / "benchmarks")
  found = index.entries()
  assert [(e.name, e.path) for e in found] == [("answer", study / "answer.md"), ("speed", bench / "speed.md")]
  text = index.render()
  assert "| [answer.md](../experiments/studies/s/results/answer.md) |" in text and "| answer.png |" in text
  assert "| [speed.md](results/speed.md) |" in text
  (study / "speed.md").write_text(head.format("speed"))
  with pytest.raises(ValueError, match="named twice: speed"):
    index.entries()


def test_benchmarks_keep_performance_results_only_and_each_study_its_own():
  """A file in ``benchmarks/results`` was written by a benchmark; one in a study's ``results/`` by
  that study's command (as typed today: a module that moved is named where it lives)."""
  found = index.entries()
  for e in found:
    folder = e.path.parent.relative_to(index.ROOT).as_posix()
    command = index.as_typed_today(e.command, found)
    if folder == "benchmarks/results":
      assert command.startswith("python -m benchmarks."), (e.name, command)
    else:
      study = folder.removeprefix("experiments/studies/").removesuffix("/results")
      assert command.split()[:3] == ["python", "-m", f"experiments.studies.{study}"], (e.name, folder, command)


def _tree(root, files):
  for path, text in files.items():
    (root / path).parent.mkdir(parents=True, exist_ok=True)
    (root / path).write_text(text)


def test_the_closure_follows_every_import_and_nothing_outside_the_project(tmp_path):
  """Checked against a hand-listed closure of a small made-up project."""
  _tree(tmp_path, {
      "benchmarks/__init__.py": "", "benchmarks/thing.py": "import numpy\nfrom nlosjax import a\n"
                                                          "def f():\n  from experiments.c import g\n",
      "nlosjax/__init__.py": "", "nlosjax/a.py": "from . import b\n", "nlosjax/b.py": "import os\n",
      "nlosjax/unused.py": "", "experiments/__init__.py": "", "experiments/c.py": "from nlosjax.b import x\n"})
  got = index.code_closure(["benchmarks.thing"], tmp_path)
  assert got == {"benchmarks/__init__.py", "benchmarks/thing.py", "nlosjax/__init__.py", "nlosjax/a.py",
                 "nlosjax/b.py", "experiments/__init__.py", "experiments/c.py"}


def test_touched_names_the_files_whose_command_runs_changed_code_and_not_for_docs(tmp_path, monkeypatch):
  """In a throwaway repository: a code edit to a module a command imports touches its results file;
  a docstring or comment edit, or an edit to a module it does not import, touches none."""
  _tree(tmp_path, {
      "benchmarks/__init__.py": "", "benchmarks/speed.py": "from nlosjax import a\n",
      "nlosjax/__init__.py": "", "nlosjax/a.py": '"""Doc."""\nX = 1  # c\n', "nlosjax/other.py": "Y = 1\n",
      "benchmarks/results/speed.md": "# S\n\nProduced by `python -m benchmarks.speed`.\n\n- Date: 2026-01-02\n"
                                     "- Machine: M\n- Commit: 1\n"})
  git = lambda *a: subprocess.run(["git", *a], cwd=tmp_path, check=True, capture_output=True)  # noqa: E731
  git("init", "-q")
  git("add", ".")
  git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "base")
  monkeypatch.setattr(index, "ROOT", tmp_path)
  monkeypatch.setattr(index, "RESULTS", tmp_path / "benchmarks" / "results")
  monkeypatch.setattr(index, "results_folders", lambda: [tmp_path / "benchmarks" / "results"])
  for edit in ('"""Other doc."""\nX = 1  # other comment\n', '"""Doc."""\n\nX = 1\n'):
    (tmp_path / "nlosjax" / "a.py").write_text(edit)
    assert index.touched("HEAD") == [], edit
  (tmp_path / "nlosjax" / "other.py").write_text("Y = 2\n")
  assert index.touched("HEAD") == []
  (tmp_path / "nlosjax" / "a.py").write_text('"""Doc."""\nX = 2\n')
  assert index.touched("HEAD") == ["benchmarks/results/speed.md"]
