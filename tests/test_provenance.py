"""Results files name the commit they ran at; benchmark output alone does not make it '+changes'."""

import shutil
import subprocess

import pytest

from experiments.provenance import git_commit, provenance


def _git(repo, *args):
  subprocess.run(["git", *args], cwd=repo, check=True, capture_output=True)


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git")
def test_git_commit_ignores_results_files_and_run_states_but_not_code(tmp_path):
  _git(tmp_path, "init", "-q")
  (tmp_path / "benchmarks" / "results").mkdir(parents=True)
  (tmp_path / "experiments" / "studies" / "s" / "results").mkdir(parents=True)
  (tmp_path / "experiments" / "studies" / "s" / "results" / "b.md").write_text("old\n")
  (tmp_path / "experiments" / "studies" / "s" / "state").mkdir()
  (tmp_path / "experiments" / "studies" / "s" / "state" / "run.jsonl").write_text("old\n")
  (tmp_path / "code.py").write_text("x = 1\n")
  (tmp_path / "benchmarks" / "results" / "a.md").write_text("old\n")
  _git(tmp_path, "add", ".")
  _git(tmp_path, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "init")
  head = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=tmp_path, check=True,
                        capture_output=True, text=True).stdout.strip()
  assert git_commit(tmp_path) == head
  (tmp_path / "benchmarks" / "results" / "a.md").write_text("new\n")   # a benchmark wrote this
  assert git_commit(tmp_path) == head
  (tmp_path / "experiments" / "studies" / "s" / "results" / "b.md").write_text("new\n")   # a study wrote this
  assert git_commit(tmp_path) == head
  (tmp_path / "experiments" / "studies" / "s" / "state" / "run.jsonl").write_text("new\n")   # a long run's pause
  assert git_commit(tmp_path) == head
  (tmp_path / "code.py").write_text("x = 2\n")                          # the code differs
  assert git_commit(tmp_path).startswith(head + " +changes")


def test_provenance_names_command_date_machine_and_commit():
  lines = provenance("python -m benchmarks.something --flag")
  text = "\n".join(lines)
  assert lines[0] == "Produced by `python -m benchmarks.something --flag`."
  for needle in ("- Date: ", "- Machine: ", "- Commit: ", "- Load average"):
    assert needle in text, needle


def test_cpu_facts_name_the_model_clock_and_cache(monkeypatch):
  from experiments import provenance as P
  cpuinfo = {"model name": "AMD EPYC", "cpu MHz": "2596.132", "cache size": "1024 KB"}
  monkeypatch.setattr(P, "_proc_field", lambda path, key: cpuinfo.get(key) if "cpuinfo" in path else None)
  monkeypatch.setattr(P, "_lscpu", lambda: {"CPU max MHz": "3000.0", "L3 cache": "32 MiB (1 instance)"})
  assert P.cpu_facts() == {"model": "AMD EPYC", "mhz": 2596.1, "cache": "1024 KB"}
  assert P.cpu_text() == "AMD EPYC, 2596 MHz, cache 1024 KB"
  assert "- Machine: AMD EPYC; 2596 MHz, cache 1024 KB; " in "\n".join(P.provenance("python -m x"))
  record = P.machine_record()
  assert (record["cpu"], record["cpu_mhz"], record["cpu_cache"]) == ("AMD EPYC", 2596.1, "1024 KB")
  # Without them in /proc/cpuinfo (an ARM machine, say), lscpu's; without either, the model alone.
  del cpuinfo["cpu MHz"], cpuinfo["cache size"]
  assert P.cpu_text() == "AMD EPYC, 3000 MHz, cache L3 32 MiB (1 instance)"
  monkeypatch.setattr(P, "_lscpu", lambda: {})
  assert P.cpu_text() == "AMD EPYC" and P.cpu_text(model=False) == ""
  assert P._clock_and_cache() == ""                 # the header then reads "AMD EPYC; 2 usable cores"


def test_the_main_job_benchmark_records_clock_cache_and_hit_rate(tmp_path):
  from benchmarks import main_job
  row = {"commit": "abc", "date": "2026-11-28T00:00:00+00:00", "install_s": 20.0, "main_job_s": 500.0,
         "load_before": "0.00", "load_after": "1.00"}
  rows, ok = main_job.verdicts({"AMD EPYC": {**row, "cpu_mhz": 2596.1, "cpu_cache": "1024 KB"},
                                "Intel(R) Xeon(R) Processor": row})
  assert rows[0].startswith("| AMD EPYC | 2596 MHz, cache 1024 KB | abc | 2026-11-28 | 20 s |")
  assert rows[1].startswith("| Intel(R) Xeon(R) Processor | not recorded | abc |")      # an older row
  assert ok and all(r.count("|") == 9 for r in rows)
  log = tmp_path / "main_job.log"
  log.write_text("pip ...\nXLA compilation cache .cache/xla: 0 of 9 compiles read from it (0%), 0 s of "
                 "compiling saved\ntrained\nXLA compilation cache .cache/xla: 3 of 12 compiles read from it\n")
  assert main_job.last_cache_line(log) == "XLA compilation cache .cache/xla: 3 of 12 compiles read from it"
  assert main_job.last_cache_line(tmp_path / "none.log") is None


def test_the_main_job_benchmark_tables_each_cpu_models_phases(tmp_path):
  """Phases read from a job's ``phases.json`` (none for a commit before it), tabled by name in order."""
  import json

  from benchmarks import main_job
  assert main_job.read_phases(tmp_path / "absent.json") == {}
  path = tmp_path / "phases.json"
  path.write_text(json.dumps({"phases_s": {"dataset": 98.4, "train ours_s": 180.0, "train ours": 320.2},
                              "total_s": 660.0, "other_s": 61.4}))
  xeon = {"commit": "new", **main_job.read_phases(path)}
  epyc = {"commit": "old", "phases_s": {"dataset": 90.0, "test split": 30.0}, "other_s": 5.0}
  lines = main_job.phase_table({"Intel(R) Xeon(R) Processor": xeon, "AMD EPYC": epyc,
                                "Other": {"commit": "older"}})
  assert lines[2] == "| CPU | commit | dataset | train ours_s | train ours | test split | other |"
  assert lines[4] == "| Intel(R) Xeon(R) | new | 98 | 180 | 320 | — | 61 |"
  assert lines[5] == "| AMD EPYC | old | 90 | — | — | 30 | 5 |"
  assert len(lines) == 7 and lines[-1] == ""            # the row without phases is left out
  assert main_job.phase_table({"AMD EPYC": {"commit": "older"}}) == []
