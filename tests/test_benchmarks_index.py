"""``benchmarks/README.md`` is generated from the results files' headers, and each file says whether it is current."""

import pytest

from benchmarks import index
from experiments import provenance


def test_the_committed_index_is_what_the_results_files_say():
  assert index.comparable(index.INDEX.read_text()) == index.comparable(index.render()), (
      "benchmarks/README.md is out of date: run python -m benchmarks.index")


def test_every_results_file_names_its_command_date_machine_commit_and_code_digest():
  for e in index.entries():
    assert e.command.startswith("python -m "), e
    assert e.date[:4].isdigit() and e.machine != "?" and e.commit != "?", e
    assert len(e.digest) == 12 and e.modules, f"{e.name}.md has no code digest (rerun the command its header names)"
  for e in index.entries():
    assert "Still holds at" not in e.path.read_text(), f"{e.name}.md: the digest replaces hand-written banners"


def test_a_header_is_read_as_written_and_a_file_without_a_command_is_refused(tmp_path):
  line = provenance.code_line(["nlosjax/a.py", "nlosjax/__init__.py"], "0123456789ab")
  (tmp_path / "thing.md").write_text(
      "# A thing\n\nProduced by `python -m benchmarks.thing --fast`.\n\n- Date: 2026-01-02T03:04:05+00:00\n"
      f"- Machine: Some CPU; 2 usable cores\n- Commit: 0123456789ab +changes\n{line}\n")
  (tmp_path / "thing.json").write_text("{}")
  (tmp_path / "plain.md").write_text("# Plain\n\nProduced by `python -m p`.\n\n- Date: 2026-01-01\n"
                                     "- Machine: M\n- Commit: 1\n")
  (tmp_path / "thing_more.md").write_text("# More\n\nProduced by `python -m x` on 2026-02-03 (5 s).\n"
                                          "- CPU: Other CPU; 4 cores\n")
  (tmp_path / "thing_more.png").write_bytes(b"")
  plain, a, b = index.entries(tmp_path)
  assert (plain.digest, plain.modules) == ("", ())
  assert index.state(plain) == "no code digest"
  assert a == index.Entry("thing", "A thing", "python -m benchmarks.thing --fast", "2026-01-02T03:04:05+00:00",
                          "Some CPU", "0123456789ab +changes", "0123456789ab",
                          ("nlosjax/__init__.py", "nlosjax/a.py"))
  assert (b.date, b.machine, b.commit) == ("2026-02-03", "Other CPU", "?")
  assert index.companions(tmp_path, "thing") == ["thing.json"]       # thing_more.png is the other's
  assert index.companions(tmp_path, "thing_more") == ["thing_more.png"]
  (tmp_path / "bad.md").write_text("# No command\n")
  with pytest.raises(ValueError, match="Produced by"):
    index.entries(tmp_path)


def test_the_digest_sees_code_but_not_comments_docstrings_or_layout():
  files = {"nlosjax/a.py": '"""Doc."""\nX = 1\n\ndef f(x):\n  """Doc."""\n  return x + X\n'}
  read = files.__getitem__
  d0 = provenance.code_digest(files, read)
  files["nlosjax/a.py"] = ('"""Other doc."""\n# a comment\nX = 1\n\n\ndef f(x):\n    """More."""\n'
                           '    return x + X  # c\n')
  assert provenance.code_digest(files, read) == d0
  files["nlosjax/a.py"] = '"""Doc."""\nX = 2\n\ndef f(x):\n  return x + X\n'
  assert provenance.code_digest(files, read) != d0


def test_the_module_closure_follows_every_import_and_nothing_outside_the_project():
  files = {
      "nlosjax/__init__.py": "",
      "nlosjax/a.py": "import numpy\nfrom nlosjax import b\n",
      "nlosjax/b.py": "def f():\n  from .sub import c   # a lazy, relative import\n  return c\n",
      "nlosjax/sub/__init__.py": "",
      "nlosjax/sub/c.py": "import importlib\nimportlib.import_module(f'{__name__}.x')\n",
      "nlosjax/sub/d.py": "",
      "nlosjax/unused.py": "",
      "experiments/__init__.py": "",
      "experiments/provenance.py": "",            # writes headers, not numbers: never part of a digest
      "benchmarks/thing.py": "from experiments import provenance\nimport nlosjax.a\n",
  }
  got = provenance.code_modules(["benchmarks.thing"], files, files.__getitem__)
  assert got == ["benchmarks/thing.py", "experiments/__init__.py", "nlosjax/__init__.py", "nlosjax/a.py",
                 "nlosjax/b.py", "nlosjax/sub/__init__.py", "nlosjax/sub/c.py", "nlosjax/sub/d.py"]


def test_a_file_is_current_while_its_code_is_unchanged_and_stale_after():
  modules = provenance.code_modules(["benchmarks.scan"])
  now = index.Entry("scan", "t", "python -m benchmarks.scan", "d", "m", "HEAD", provenance.code_digest(modules),
                    tuple(modules))
  assert index.state(now) == "current"
  old = index.Entry(**{**now.__dict__, "digest": "000000000000"})
  assert index.state(old).startswith("stale")
  line = provenance.code_line(modules)
  assert provenance.CODE_LINE.search(line).group(1) == now.digest


def test_the_digest_text_is_python_3_11s_ast_dump_on_every_python():
  # Written out by hand from Python 3.11's ast.dump(annotate_fields=False): 3.12 adds an empty
  # type_params to functions and classes and an empty piece to a nested f-string format, 3.13
  # leaves empty lists out; the digest must not see any of that (the GPU image runs 3.12).
  source = 'def f(x):\n  "doc"\n  return f"{x:{w}}"\nclass C:\n  pass\n'
  assert provenance._behaviour(source) == (
      "Module([FunctionDef('f', arguments([], [arg('x')], kwonlyargs=[], kw_defaults=[], defaults=[]), "
      "[Return(JoinedStr([FormattedValue(Name('x', Load()), -1, JoinedStr([FormattedValue(Name('w', Load()), "
      "-1)]))]))], []), ClassDef('C', [], [], [Pass()], [])], [])")


def test_a_digest_written_by_another_python_is_recomputed_from_its_commit():
  import subprocess
  module = "nlosjax/stats.py"
  if subprocess.run(["git", "diff", "--quiet", "HEAD", "--", module], cwd=provenance.ROOT).returncode:
    pytest.skip(f"{module} has uncommitted edits")
  commit = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=provenance.ROOT,
                          capture_output=True, text=True, check=True).stdout.strip()
  text = f"# T\n\n- Commit: {commit}\n{provenance.code_line([module], '0' * 12)}\n- Date: x\n"
  new = provenance.recompute_at_commit(text)
  assert provenance.CODE_LINE.search(new).group(1) == provenance.code_digest([module])
  assert "`000000000000` for the same code" in new and new.endswith("- Date: x\n")
  assert provenance.recompute_at_commit(new) is None                     # already right: unchanged
  assert provenance.recompute_at_commit(text.replace(commit, commit + " +changes")) is None
  with pytest.raises(ValueError, match="git has no nlosjax/stats.py at commit 0000000"):
    provenance.recompute_at_commit(text.replace(commit, "0000000"))


def test_results_are_read_from_benchmarks_and_each_studys_folder_and_a_name_is_one_file(tmp_path, monkeypatch):
  """Performance results in ``benchmarks/results``, each study's in its own ``results/``; the index
  links each where it lies, and a name in two folders is refused (records name files by stem)."""
  from benchmarks import results_header
  bench, study = tmp_path / "benchmarks" / "results", tmp_path / "experiments" / "studies" / "s" / "results"
  for folder in (bench, study, tmp_path / "experiments" / "studies" / "t"):      # t keeps no results
    folder.mkdir(parents=True)
  assert results_header.results_folders(tmp_path) == [bench, study]
  head = "# {0}\n\nProduced by `python -m {0}`.\n\n- Date: 2026-01-02\n- Machine: M\n- Commit: 1\n"
  (bench / "speed.md").write_text(head.format("speed"))
  (study / "answer.md").write_text(head.format("answer"))
  (study / "answer.png").write_bytes(b"")
  monkeypatch.setattr(index, "results_folders", lambda: results_header.results_folders(tmp_path))
  monkeypatch.setattr(index, "HERE", tmp_path / "benchmarks")
  found = index.entries()
  assert [(e.name, e.path) for e in found] == [("answer", study / "answer.md"), ("speed", bench / "speed.md")]
  text = index.render(computed={"answer": "current", "speed": "current"})
  assert "| [answer.md](../experiments/studies/s/results/answer.md) |" in text and "| answer.png |" in text
  assert "| [speed.md](results/speed.md) |" in text
  (study / "speed.md").write_text(head.format("speed"))
  with pytest.raises(ValueError, match="named twice: speed"):
    index.entries()


def test_benchmarks_keep_performance_results_only_and_each_study_its_own():
  """A file in ``benchmarks/results`` was written by a benchmark; one in a study's ``results/`` by
  that study's command (as typed today)."""
  from benchmarks.equivalence import as_moved
  for e in index.entries():
    folder = e.path.parent.relative_to(provenance.ROOT).as_posix()
    command = as_moved(e.command)
    if folder == "benchmarks/results":
      assert command.startswith("python -m benchmarks."), (e.name, command)
    else:
      study = folder.removeprefix("experiments/studies/").removesuffix("/results")
      assert command.split()[:3] == ["python", "-m", f"experiments.studies.{study}"], (e.name, folder, command)
