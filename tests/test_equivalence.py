"""Results carried forward: the probe comparison, and the rule by which the index carries a stale file."""

import json
import pathlib
import subprocess

import numpy as np
import pytest

from benchmarks import equivalence, index, results_header
from experiments import provenance

#: A landed commit (the last before the carry-forward rule existed); every clone of main has it.
BASE = "f4a2ccf"


def test_compare_tells_identical_rounding_moved_added_and_missing_arrays():
  a = np.linspace(-2, 2, 50, dtype=np.float32)
  old = {"train/ours/w": a, "train/ours/b": a, "data/lct/x": np.arange(5), "evaluate/fbp/psnr": a,
         "physics/lct": a.copy(), "pretrained/x/y": np.array([1.0, np.nan])}
  new = {"train/ours/w": a.copy(), "train/ours/b": a * (1 + 1e-7), "data/lct/x": np.arange(5),
         "evaluate/fbp/psnr": a, "evaluate/fbp/psnr_zero": a, "physics/lct": a + 1e-3,
         "pretrained/x/y": np.array([np.nan, 1.0])}
  rows = {r["probe"]: r for r in equivalence.compare(old, new)}
  assert rows["train/ours"]["identical"] == 1 and rows["train/ours"]["arrays"] == 2
  assert 0 < rows["train/ours"]["worst"] <= 2e-7 and rows["train/ours"]["passed"]
  assert rows["data/lct"]["passed"] and rows["data/lct"]["identical"] == 1
  assert rows["evaluate/fbp"]["passed"] and rows["evaluate/fbp"]["added"] == ["evaluate/fbp/psnr_zero"]
  assert not rows["physics/lct"]["passed"] and rows["physics/lct"]["worst"] == pytest.approx(5e-4, rel=1e-3)
  assert not rows["pretrained/x"]["passed"]                     # NaN moved
  gone = {r["probe"]: r for r in equivalence.compare(old, {k: v for k, v in new.items() if k != "data/lct/x"})}
  assert not gone["data/lct"]["passed"] and gone["data/lct"]["missing"] == ["data/lct/x"]


def _record(tmp_path, *, passed=True, leave_out=(), base=BASE, name="equivalence"):
  closure = [m for m in provenance.code_modules(["benchmarks.equivalence", "benchmarks.equivalence_probe"])
             if m not in leave_out]
  (tmp_path / f"{name}.md").write_text(
      "# Results carried forward\n\nProduced by `python -m benchmarks.equivalence --base x`.\n\n"
      "- Date: 2026-12-01T00:00:00+00:00\n- Machine: M\n- Commit: abc\n" + provenance.code_line(closure) + "\n")
  (tmp_path / f"{name}.json").write_text(json.dumps({"base": base, "passed": passed}))


def _entry(modules, digest):
  return index.Entry("thing", "T", "python -m x", "2026", "M", BASE, digest, tuple(sorted(modules)))


def _digest_at(commit, modules):
  files = results_header.GitFiles()
  try:
    return provenance.code_digest(modules, lambda p: files(commit, p))
  finally:
    files.close()


def test_a_file_current_at_the_base_whose_changes_the_check_ran_is_carried_forward(tmp_path):
  if results_header.git_output("cat-file", "-e", f"{BASE}^{{commit}}") is None:
    pytest.skip(f"this clone lacks commit {BASE} (a shallow clone)")
  _record(tmp_path)
  inside = ["nlosjax/train/loop.py", "nlosjax/metrics.py"]           # changed since BASE, both probed
  carried = _entry(inside, _digest_at(BASE, inside))
  assert equivalence.carried_forward(carried, results=tmp_path) == f"carried forward from {BASE} by equivalence.md"
  # Not current at the base: nothing to carry.
  assert equivalence.carried_forward(_entry(inside, "0" * 12), results=tmp_path) is None
  # A module that changed since the base but lies outside what the check ran: not carried (a
  # record whose closure leaves out experiments/train.py, changed since BASE).
  outside = inside + ["experiments/train.py"]
  assert equivalence.carried_forward(_entry(outside, _digest_at(BASE, outside)), results=tmp_path) is not None
  _record(tmp_path, leave_out=("experiments/train.py",))
  assert equivalence.carried_forward(_entry(outside, _digest_at(BASE, outside)), results=tmp_path) is None
  assert equivalence.carried_forward(carried, results=tmp_path) is not None
  # A check that failed carries nothing.
  _record(tmp_path, passed=False)
  assert equivalence.carried_forward(carried, results=tmp_path) is None
  # Nor does a check whose own code changed since it ran.
  _record(tmp_path)
  md = tmp_path / "equivalence.md"
  md.write_text(md.read_text().replace("- Code: `", "- Code: `f"))
  assert equivalence.carried_forward(carried, results=tmp_path) is None


def test_records_against_one_base_cover_the_union_of_their_closures(tmp_path):
  """A file whose changes lie partly in the main probe's closure, partly in the measured probe's,
  is carried only with both records at the base, and by no record that failed."""
  if results_header.git_output("cat-file", "-e", f"{BASE}^{{commit}}") is None:
    pytest.skip(f"this clone lacks commit {BASE} (a shallow clone)")
  both = ["nlosjax/train/loop.py", "experiments/train.py"]            # both changed since BASE
  entry = _entry(both, _digest_at(BASE, both))
  _record(tmp_path, leave_out=("experiments/train.py",))
  assert equivalence.carried_forward(entry, results=tmp_path) is None
  _record(tmp_path, leave_out=("nlosjax/train/loop.py",), name="equivalence_measured")
  assert equivalence.carried_forward(entry, results=tmp_path) == \
      f"carried forward from {BASE} by equivalence.md + equivalence_measured.md"
  _record(tmp_path, leave_out=("nlosjax/train/loop.py",), name="equivalence_measured", passed=False)
  assert equivalence.carried_forward(entry, results=tmp_path) is None
  # A failed record stops its base: the other's static closure must not stand in for it.
  _record(tmp_path, leave_out=(), name="equivalence_measured")
  assert equivalence.carried_forward(entry, results=tmp_path) is not None
  _record(tmp_path, passed=False)
  assert equivalence.carried_forward(entry, results=tmp_path) is None
  _record(tmp_path, leave_out=("experiments/train.py",))
  # Records against another base never join: the union is of one base's records.
  _record(tmp_path, leave_out=("nlosjax/train/loop.py",), name="equivalence_measured", base="0" * 40)
  assert equivalence.carried_forward(entry, results=tmp_path) is None


def test_the_base_tree_runs_todays_weights_and_names_those_shipped_since(tmp_path):
  src = provenance.ROOT / "nlosjax" / "weights"
  names = sorted(p.name for p in src.iterdir() if p.is_dir())
  tree = tmp_path / "base"
  for n in names:                                # the base: every network as today's but one
    (tree / "nlosjax" / "weights" / n).mkdir(parents=True)
    for f in (src / n).iterdir():
      (tree / "nlosjax" / "weights" / n / f.name).write_bytes(f.read_bytes())
  first = tree / "nlosjax" / "weights" / names[0] / "params.npz"
  first.write_bytes(b"older weights")
  (tree / "nlosjax" / "weights" / "gone").mkdir()
  assert equivalence.use_todays_weights(tree) == [names[0]]
  assert first.read_bytes() == (src / names[0] / "params.npz").read_bytes()
  assert not (tree / "nlosjax" / "weights" / "gone").exists()


def test_a_second_record_carries_a_file_current_at_its_own_base(tmp_path):
  later = results_header.git_output("rev-parse", "--short=7", "HEAD~1")
  if later is None or results_header.git_output("cat-file", "-e", f"{BASE}^{{commit}}") is None:
    pytest.skip("this clone lacks the commits (a shallow clone)")
  later = later.strip()
  inside = ["nlosjax/train/loop.py", "nlosjax/metrics.py"]
  at_later = _entry(inside, _digest_at(later, inside))
  _record(tmp_path)                                        # the record against BASE alone
  if _digest_at(later, inside) != _digest_at(BASE, inside):
    assert equivalence.carried_forward(at_later, results=tmp_path) is None
  _record(tmp_path, base=later, name=f"equivalence_{later}")
  assert equivalence.records(tmp_path) == ["equivalence", f"equivalence_{later}"]
  assert equivalence.carried_forward(at_later, results=tmp_path) is not None
  # A record is never carried by another.
  assert equivalence.carried_forward(index.Entry(f"equivalence_{later}", "T", "x", "2026", "M", BASE, "0" * 12,
                                                 tuple(inside)), results=tmp_path) is None


def test_several_bases_run_todays_probe_once_and_write_a_record_each(tmp_path, monkeypatch):
  """``--base A B``: today's tree probed once, each base's tree once, one record per base."""
  probed, worktrees = [], []
  arrays = {"data/lct/x": np.arange(3.0)}

  def fake_probe(tree, out, *, log=print, probe=equivalence.PROBE):
    probed.append(pathlib.Path(tree).name)
    return dict(arrays)

  def fake_run(cmd, **kw):
    if cmd[:2] == ["git", "rev-parse"]:
      return subprocess.CompletedProcess(cmd, 0, stdout=cmd[2] * 4 + "\n", stderr="")
    if cmd[:3] == ["git", "worktree", "add"]:
      worktrees.append(cmd[-1])
      pathlib.Path(cmd[-2]).mkdir(parents=True)
    return subprocess.CompletedProcess(cmd, 0, stdout="", stderr="")

  monkeypatch.setattr(equivalence, "run_probe", fake_probe)
  monkeypatch.setattr(equivalence, "use_todays_weights", lambda tree: [])
  monkeypatch.setattr(equivalence, "changed_modules", lambda base: [])
  monkeypatch.setattr(equivalence.subprocess, "run", fake_run)
  outs = [str(tmp_path / "equivalence.md"), str(tmp_path / "equivalence_bbb.md")]
  assert equivalence.main(["--base", "aaa", "bbb", "--out", *outs]) == 0
  assert worktrees == ["aaa" * 4, "bbb" * 4]
  assert probed.count(provenance.ROOT.name) == 1 and len(probed) == 3
  for out, base in zip(outs, ("aaa" * 4, "bbb" * 4)):
    record = json.loads(pathlib.Path(out).with_suffix(".json").read_text())
    assert record["base"] == base and record["passed"]
    assert "--base aaa bbb" in pathlib.Path(out).read_text()
  assert equivalence.record_name("bbb", False) == "equivalence_bbb.md"
  with pytest.raises(SystemExit):
    equivalence.main(["--base", "aaa", "bbb", "--out", outs[0]])


def test_a_module_moved_verbatim_is_judged_at_its_new_path(tmp_path, monkeypatch):
  before = "b9dbfc3"                  # the last commit before MOVES' modules left nlosjax
  if results_header.git_output("cat-file", "-e", f"{before}^{{commit}}") is None:
    pytest.skip(f"this clone lacks commit {before} (a shallow clone)")
  # The mechanism study's probe moved unchanged, the study moved out of benchmarks/ and its
  # import of the probe was rewritten; neither lies in the check's closure, so only the move
  # rule carries the file.
  modules = ["nlosjax/models/probe.py", "benchmarks/mechanisms/study.py"]     # as the base names them
  entry = _entry(modules, _digest_at(before, modules))
  # Today's text as of a commit the study had changed only by the move (later edits of its code
  # are the rule's business, not this test's).
  after = "f2a4186"
  if results_header.git_output("cat-file", "-e", f"{after}^{{commit}}") is None:
    pytest.skip(f"this clone lacks commit {after} (a shallow clone)")
  monkeypatch.setattr(equivalence, "today_text", lambda p: results_header.git_output("show", f"{after}:{p}"))
  _record(tmp_path, base=before)
  assert "experiments/studies/mechanisms/probe.py" not in provenance.code_modules(
      ["benchmarks.equivalence", "benchmarks.equivalence_probe"])
  assert equivalence.carried_forward(entry, results=tmp_path) == f"carried forward from {before} by equivalence.md"
  monkeypatch.setattr(equivalence, "MOVES", {})
  assert equivalence.carried_forward(entry, results=tmp_path) is None
  # The rewrite renames imports of the moved module only.
  monkeypatch.setattr(equivalence, "MOVES", {"a/b/c.py": "d/e.py"})
  assert equivalence.as_moved("from a.b import c as x\nimport a.b.c\nfrom a.b.cd import y\n") == \
      "from d import e as x\nimport d.e\nfrom a.b.cd import y\n"
  monkeypatch.setattr(equivalence, "MOVES", {"b/s/": "e/t/s/"})
  assert equivalence.moved_path("b/s/x.py") == "e/t/s/x.py" and equivalence.moved_path("b/sx.py") == "b/sx.py"
  assert equivalence.as_moved('"python -m b.s.cli; see b/s/state and ``b/s``"\nfrom b import s\n') == \
      '"python -m e.t.s.cli; see e/t/s/state and ``e/t/s``"\nfrom e.t import s\n'
  # A module made a package (its code now the package's __init__.py) keeps its dotted name.
  monkeypatch.setattr(equivalence, "MOVES", {"s/a.py": "s/a/__init__.py", "b/a.py": "s/a/__init__.py"})
  assert equivalence.moved_path("s/a.py") == "s/a/__init__.py"
  assert equivalence.as_moved("from s import a\nimport s.a\nfrom b import a\nx = 's/a.py'\n") == \
      "from s import a\nimport s.a\nfrom s import a\nx = 's/a/__init__.py'\n"
  monkeypatch.setattr(equivalence, "MOVES", {"a/b/c.py": "d/e.py"})
  # A run of imports the linter re-sorted after the rename does what the base's did; other
  # reorderings of code do not count as the same.
  base = "def f():\n  from nlosjax import metrics\n  from a.b import c as P\n  from a import z\n  return P\n"
  today = "def f():\n  from a import z\n  from d import e as P\n  from nlosjax import metrics\n  return P\n"
  assert equivalence.same_moved_code(base, today, "x.py")
  assert not equivalence.same_moved_code(base, today.replace("return P", "return z"), "x.py")
  assert equivalence.same_moved_code("from a import x\nfrom a import y\n", "from a import x, y\n", "x.py")
  assert not equivalence.same_moved_code("x = 1\ny = 2\n", "y = 2\nx = 1\n", "x.py")
  # A function renamed everywhere is the same code; a caller left on the old name is not.
  monkeypatch.setattr(equivalence, "RENAMED", {"adapt_to_capture": "for_capture"})
  assert equivalence.same_moved_code("v = cio.adapt_to_capture(m, s)\n", "v = cio.for_capture(m, s)\n", "x.py")
  assert not equivalence.same_moved_code("v = cio.adapt_to_capture(m, s)\n", "v = cio.for_capture(m, t)\n", "x.py")


def test_the_measured_probe_keeps_every_table_number_but_the_seconds():
  """The report's tables, read as the measured probe reads them: a hand-written report."""
  from benchmarks import equivalence_probe_measured as M
  report = "\n".join([
      "# Title 64 x 64", "",
      "| method | vs FBP 64 × 64 | mean |", "|---|---|---|",
      "| LCT | 15.82 / 0.498 | **15.82 / 0.498** |", "| Zero | 5.90 / – | 5.90 / – |", "",
      "Seconds per scan 12.5", "",
      "| method | 16 × 16 first | 16 × 16 per frame | 8 × 8 first |", "|---|---|---|---|",
      "| CSA | 10.23 | 9.74 | 9.91 |", "",
      "| network | input | exit_sign | s per scan |", "|---|---|---|---|",
      "| Ours | 16 × 16 | 14.17 → 14.92 | 14.5 |"])
  out = {}
  M.table_arrays(report, out)
  assert sorted(out) == ["measured/report/00-00", "measured/report/00-01", "measured/report/02-00"]
  np.testing.assert_array_equal(out["measured/report/00-00"], [15.82, 0.498, 15.82, 0.498])
  np.testing.assert_array_equal(out["measured/report/00-01"], [5.90, 5.90])
  assert "measured/report/01-00" not in out                     # a table of seconds alone
  np.testing.assert_array_equal(out["measured/report/02-00"], [16, 16, 14.17, 14.92])
  scores = {}
  M.json_arrays({"exit_sign": {"fbp@4": {"psnr": 12.5, "time_s": 3.0, "vs": {"lct": {"ssim": 0.5}}}},
                 "list": [1, 2.5], "none": None, "flag": True, "warm": {"x": 1.0}}, "measured/scores", scores)
  assert sorted(scores) == ["measured/scores/exit_sign/fbp@4/psnr", "measured/scores/exit_sign/fbp@4/vs/lct/ssim",
                            "measured/scores/list"]
  np.testing.assert_array_equal(scores["measured/scores/list"], [1, 2.5])


def test_a_record_that_compared_nothing_fails(tmp_path):
  """A base without the probed code writes no array: every row is added since, none compared,
  and the record must not pass (it would carry files by a closure it never ran)."""
  rows = equivalence.compare({}, {"measured/scores/x": np.arange(3.0)})
  assert rows[0]["passed"] and rows[0]["arrays"] == 0
  record = equivalence.write(tmp_path / "equivalence_measured.md", "abc" * 4, rows, [], {"base": 1.0, "today": 1.0},
                             "cmd", probe=equivalence.PROBES["measured"])
  assert not record["passed"] and "nothing was compared" in (tmp_path / "equivalence_measured.md").read_text()


def test_the_measured_probe_finds_the_protocol_and_writes_records_of_its_own():
  from benchmarks import equivalence_probe_measured as M
  cli = M.protocol_cli()
  assert cli is not None and cli.__name__ == "experiments.studies.real_undersampling.__main__"
  assert equivalence.PROBES["measured"].name == "equivalence_probe_measured.py"
  assert equivalence.record_name("abc", True, "measured") == "equivalence_measured.md"
  assert equivalence.record_name("abc", False, "measured") == "equivalence_measured_abc.md"
  # Its records are records: the index carries a file by them as by the main ones.
  closure = provenance.code_modules(["benchmarks.equivalence", "benchmarks.equivalence_probe_measured"])
  assert "experiments/studies/real_undersampling/protocol.py" in closure
  assert "experiments/reconstruct.py" in closure


def test_a_records_header_names_the_closure_of_the_probe_it_ran(tmp_path):
  """The index carries a file by the modules a record's header lists: the measured probe's
  record lists the protocol, the main one does not (it never ran it)."""
  seconds = {"base": 1.0, "today": 1.0}
  for probe, holds in (("measured", True), ("main", False)):
    out = tmp_path / equivalence.record_name("abc", True, probe)
    equivalence.write(out, "abc" * 4, [], [], seconds, "cmd", probe=equivalence.PROBES[probe])
    listed = results_header.read_entry(out).modules
    assert ("experiments/studies/real_undersampling/protocol.py" in listed) is holds
    assert set(listed) == set(json.loads(out.with_suffix(".json").read_text())["closure"])


#: A landed commit whose committed index carried ``mechanisms.md`` forward (from 44695d1).
CHAIN_BASE = "3a506b4"


def test_a_file_carried_at_the_base_is_carried_on_by_records_against_that_base(tmp_path):
  """The chain: the base's own index carried the file; records against the base cover what changed since."""
  show = results_header.GitFiles()
  try:
    text = show(CHAIN_BASE, "benchmarks/results/mechanisms.md")
    said = equivalence.state_at(CHAIN_BASE, "mechanisms", show)
  finally:
    show.close()
  if text is None:
    pytest.skip(f"this clone lacks commit {CHAIN_BASE} (a shallow clone)")
  assert said == "carried forward from 44695d1 by equivalence_44695d1.md"
  own = tmp_path / "mechanisms.md"
  own.write_text(text)                                   # the file as the base held it
  entry = results_header.read_entry(own)
  assert equivalence._changed_since(entry, CHAIN_BASE, provenance.project_files()) is None  # not current there
  _, changed = equivalence._carried_at(entry, CHAIN_BASE, tmp_path, provenance.project_files())
  files = provenance.project_files()
  closure = sorted({m for m in changed if m in files} | {"nlosjax/train/loop.py"})

  def record(closure, passed=True):
    (tmp_path / "equivalence.md").write_text(
        "# Results carried forward\n\nProduced by `python -m benchmarks.equivalence --base x`.\n\n"
        "- Date: 2026-12-01T00:00:00+00:00\n- Machine: M\n- Commit: abc\n" + provenance.code_line(closure) + "\n")
    (tmp_path / "equivalence.json").write_text(json.dumps({"base": CHAIN_BASE, "passed": passed}))

  record(closure)
  if changed <= set(closure):
    assert equivalence.carried_forward(entry, results=tmp_path) == \
        f"carried forward from 44695d1 via {CHAIN_BASE} by equivalence.md"
  if changed:                                   # a changed module outside every closure stops it
    record(sorted(set(closure) - {sorted(changed)[0]}) or ["nlosjax/train/loop.py"])
    assert equivalence.carried_forward(entry, results=tmp_path) is None
  record(closure, passed=False)
  assert equivalence.carried_forward(entry, results=tmp_path) is None
  record(closure)
  own.write_text(text.replace("\n", "\n\n", 1))           # not the file the base's index judged
  assert equivalence.carried_forward(entry, results=tmp_path) is None


def test_state_at_reads_the_state_column_of_a_committed_index():
  row = ("| [x.md](results/x.md) | a \\| b | `python -m x` | 2026 | M | abc | carried forward from 1234567 by "
         "equivalence.md | goal | x.json |")
  other = "| [xy.md](results/xy.md) | t | `c` | 2026 | M | abc | stale since 1 (m) | goal |  |"
  study = "| [s.md](../experiments/studies/s/results/s.md) | t | `c` | 2026 | M | abc | **current** | goal |  |"
  show = lambda commit, path: f"# Index\n\n{other}\n{row}\n{study}\n" if path == equivalence.INDEX_PATH else None
  assert equivalence.state_at("c", "x", show) == "carried forward from 1234567 by equivalence.md"
  assert equivalence.state_at("c", "xy", show) == "stale since 1 (m)"
  assert equivalence.state_at("c", "s", show) == "**current**"     # a study's own results folder
  assert equivalence.state_at("c", "z", show) is None
  assert equivalence.state_at("c", "x", lambda commit, path: None) is None


def test_the_studies_probe_runs_the_studies_and_keeps_their_numbers_not_their_times(monkeypatch):
  """Its closure holds the studies it runs (so a change there can be carried), and it keeps every
  number of a study's record but times, machine facts and paths."""
  import sys
  monkeypatch.syspath_prepend(str(provenance.ROOT / "benchmarks"))   # as benchmarks.equivalence lays it out
  sys.modules.pop("equivalence_probe_measured", None)
  from benchmarks import equivalence_probe_studies as S
  closure = provenance.code_modules(["benchmarks.equivalence", "benchmarks.equivalence_probe_studies"])
  for m in ("experiments/studies/mechanisms/study.py", "experiments/studies/mechanisms/cli.py",
            "experiments/studies/ablations/__init__.py", "experiments/studies/tradeoff/training.py",
            "experiments/tiny_run.py"):
    assert m in closure, m
  assert equivalence.PROBES["studies"].name == "equivalence_probe_studies.py"
  out = {}
  S.leaves({"best_val_psnr": 12.5, "machine": {"cpu": 2}, "train_wall_s": 3.0, "test": {"eval_s": 1.0,
            "scores": {"psnr": [1.0, 2.5]}}, "loss_curve": [{"step": 2, "loss": 0.5, "time_s": 9.0}],
            "stop_reason": "plateau", "validation_curve": [{"step": 2, "val_psnr": 8.0, "val_s": 0.4}]},
           "studies/x", out)
  assert sorted(out) == ["studies/x/best_val_psnr", "studies/x/loss_curve/0/loss", "studies/x/loss_curve/0/step",
                         "studies/x/test/scores/psnr", "studies/x/validation_curve/0/step",
                         "studies/x/validation_curve/0/val_psnr"]
  np.testing.assert_array_equal(out["studies/x/test/scores/psnr"], [1.0, 2.5])


def test_the_scripts_probe_holds_the_scripts_it_runs_and_fingerprints_programs(monkeypatch):
  """Its closure holds the performance benchmarks and the studies it runs; a fingerprint is equal
  for equal texts and moves for any change; the tiny preset answers only its own name."""
  import sys
  monkeypatch.syspath_prepend(str(provenance.ROOT / "benchmarks"))
  sys.modules.pop("equivalence_probe_measured", None)
  from benchmarks import equivalence_probe_scripts as P
  from experiments import configs
  closure = provenance.code_modules(["benchmarks.equivalence", "benchmarks.equivalence_probe_scripts"])
  for m in ("benchmarks/compile.py", "benchmarks/dry_run.py", "benchmarks/hlo_gpu.py", "benchmarks/model.py",
            "benchmarks/step_profile.py", "benchmarks/prefetch.py", "benchmarks/depth_range.py",
            "experiments/studies/generalisation/__init__.py", "experiments/studies/preset_choice/__init__.py",
            "experiments/studies/realism/__init__.py", "experiments/studies/time_to_plateau/__init__.py",
            "experiments/studies/real_preset/study.py", "experiments/studies/align.py",
            "experiments/studies/alignment.py", "experiments/export_weights.py",
            "experiments/studies/independent_test/__init__.py", "experiments/studies/csa/__main__.py",
            "experiments/studies/stopping_replay/__init__.py"):
    assert m in closure, m
  assert equivalence.PROBES["scripts"].name == "equivalence_probe_scripts.py"
  a = P.fingerprint("module { }")
  assert a.shape == (32,) and np.array_equal(a, P.fingerprint("module { }"))
  assert equivalence.compare({"x": a}, {"x": P.fingerprint("module {  }")})[0]["passed"] is False
  with P.tiny_preset({"data": {"path": "x.h5"}}):
    assert configs.get_config(P.TINY) == {"data": {"path": "x.h5"}}
    assert configs.get_config("cpu") == configs.get_config("cpu")
  with pytest.raises(ValueError):
    configs.get_config(P.TINY)
  hlo = ('HloModule m\n\nFileNames\n1 "a.py"\n\nStackFrames\n1 {file_location_id=1 parent_frame_id=1}\n\n'
         'ENTRY e {\n  x = f32[] parameter(0), metadata={op_name="x" source_file="/a/b.py" source_line=3 '
         'stack_frame_id=1}\n}\n')
  moved = hlo.replace('"a.py"', '"c.py"').replace("/a/b.py", "/tmp/c.py").replace("source_line=3", "source_line=9")
  assert np.array_equal(P.program_fingerprint(hlo), P.program_fingerprint(moved))   # where it was traced from
  assert P.SOURCE.sub("", P.FRAMES.sub("", hlo)) == \
      'HloModule m\n\nENTRY e {\n  x = f32[] parameter(0), metadata={op_name="x"}\n}\n'
  assert not np.array_equal(P.program_fingerprint(hlo), P.program_fingerprint(hlo.replace("f32[]", "f16[]")))
  kept = []
  with P.wrapped(P, "plain", kept):
    P.plain({"a": 1})
  assert kept == [{"a": 1}] and P.plain.__name__ == "plain"
