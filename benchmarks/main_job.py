"""The README's first command, timed from a fresh clone: ``benchmarks/results/main_job.md``.

    python -m benchmarks.main_job [--out benchmarks/results/main_job.md] [--keep DIR]

Clones the committed HEAD into a temporary folder (so untracked files, git-ignored
runs and datasets do not help it), makes a fresh virtual environment with this
Python, and runs the README's command 1 there exactly as a newcomer does,
``pip install -e . && python -m experiments.train``, timing the install and the
main job separately. Writes the results file whole: provenance, the two times
against the 20-minute budget (the budget is for the main job on 2 cores), the
load average before and after (the promise is for a quiet machine: run nothing
beside it), and the headline rows of the main job's ``table.md``.

``python -m benchmarks.table1`` quotes this file's time and commit in
``table1.md``. Needs ``git`` and network access to the package index; refuses
to run with uncommitted edits to tracked code, since the clone would not have
them.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time

BUDGET_S = 1200
ROOT = pathlib.Path(__file__).resolve().parents[1]
COMMAND = "pip install -e . && python -m experiments.train"


def _run(cmd: str, cwd: pathlib.Path, env: dict, log: pathlib.Path) -> float:
  """Run ``cmd`` in bash, appending its output to ``log``; wall seconds (raises on failure)."""
  t0 = time.perf_counter()
  with open(log, "a") as f:
    proc = subprocess.run(["bash", "-c", cmd], cwd=cwd, env=env, stdout=f, stderr=subprocess.STDOUT)
  took = time.perf_counter() - t0
  if proc.returncode:
    raise SystemExit(f"`{cmd}` failed (exit {proc.returncode}) after {took:.0f} s; see {log}")
  return took


def read_time(path=ROOT / "benchmarks" / "results" / "main_job.json") -> dict | None:
  """The last measurement (``main_job.json``) or None where it was never made."""
  path = pathlib.Path(path)
  return json.loads(path.read_text()) if path.exists() else None


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--out", default="benchmarks/results/main_job.md")
  parser.add_argument("--keep", default=None, help="clone into DIR and keep it (default: a temporary folder)")
  args = parser.parse_args(argv)
  from experiments.provenance import git_commit, load_average, provenance
  commit = git_commit()
  if "+changes" in commit:
    raise SystemExit("uncommitted edits to tracked code: commit them first (the clone would not have them)")
  cmd = "python -m benchmarks.main_job " + " ".join(sys.argv[1:] if argv is None else argv)
  date = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
  facts = provenance(cmd.strip())
  load_before = load_average(", ")
  tmp = None
  if args.keep:
    where = pathlib.Path(args.keep)
  else:
    tmp = tempfile.TemporaryDirectory(prefix="nlosjax-main-job-")
    where = pathlib.Path(tmp.name)
  clone, venv, log = where / "clone", where / "venv", where / "main_job.log"
  subprocess.run(["git", "clone", "--quiet", str(ROOT), str(clone)], check=True)
  subprocess.run([sys.executable, "-m", "venv", "--clear", str(venv)], check=True)
  env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
  env["PATH"] = f"{venv / 'bin'}:{env.get('PATH', '')}"
  env["VIRTUAL_ENV"] = str(venv)
  print(f"main job: installing and running `{COMMAND}` in {clone} (log: {log})", flush=True)
  install_s = _run("pip install -q -e .", clone, env, log)
  job_s = _run("python -m experiments.train", clone, env, log)
  table = (clone / "runs" / "default" / "results" / "table.md").read_text()
  load_after = load_average(", ")
  verdict = "within" if job_s <= BUDGET_S else "OVER"
  lines = ["# The main job from a fresh clone", ""] + facts + [
      f"- Load average before the clone: {load_before}; after the job: {load_after}", "",
      f"README command 1, `{COMMAND}`, in a fresh clone of the commit above and a fresh virtual "
      "environment (the install resolves the newest versions `pyproject.toml` allows):", "",
      "| step | wall time |", "|---|---|",
      f"| `pip install -e .` (downloads included) | {install_s:.0f} s |",
      f"| `python -m experiments.train` (data, training, evaluation) | {job_s:.0f} s = {job_s / 60:.1f} min |",
      "",
      f"The main job is **{verdict}** its budget of {BUDGET_S} s (20 min on 2 cores).", "",
      "## The main job's table (`runs/default/results/table.md`, 1 training seed)", "", table]
  out = pathlib.Path(args.out)
  out.parent.mkdir(parents=True, exist_ok=True)
  out.write_text("\n".join(lines))
  out.with_suffix(".json").write_text(json.dumps(
      {"commit": commit, "date": date, "install_s": round(install_s, 1),
       "main_job_s": round(job_s, 1), "budget_s": BUDGET_S, "load_before": load_before,
       "load_after": load_after}, indent=2) + "\n")
  if tmp is not None:
    tmp.cleanup()
  print(out.read_text())


if __name__ == "__main__":
  main()
