"""The README's first command, timed from a fresh clone: ``benchmarks/results/main_job.md``.

    python -m benchmarks.main_job [--out benchmarks/results/main_job.md] [--keep DIR]

Clones the committed HEAD into a temporary folder (so untracked files, git-ignored
runs and datasets do not help it), makes a fresh virtual environment with this
Python, and runs the README's command 1 there exactly as a newcomer does,
``pip install -e . && python -m experiments.train``, timing the install and the
main job separately.

The 20-minute budget must hold on every CPU model the project's machines have
(``CPU_MODELS``: an AMD EPYC and a slower Intel Xeon so far), so the measurement is
kept per CPU model in ``main_job.json``: a run replaces its own model's row and
keeps the others. The results file is written whole from that JSON: provenance,
one row per CPU model (its commit, date, install and job times, load before and
after: the promise is for a quiet machine, so run nothing beside it; the CPU's clock
and cache, which tell apart machines of one model name), the verdict
for each model and for all of them together (a model never measured fails the
verdict), and the headline rows of this run's ``table.md``. CI (``.ci/run``) runs
the main job too, but only fails on a failure, a missing table or a hang: time is
this file's claim, not a test's.

The clone starts with an empty compilation cache (its own ``.cache/xla``; a
``NLOSJAX_CACHE_DIR`` or ``JAX_COMPILATION_CACHE_DIR`` of this shell is not passed on),
as a newcomer's does; the job's hit-rate line is kept with its row.

Needs ``git`` and network access to the package index; refuses
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
# The CPU models this project's machines come in (``/proc/cpuinfo``'s model name, matched by
# prefix); the budget must hold on each.
CPU_MODELS = ("AMD EPYC", "Intel(R) Xeon(R)")
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


def read_times(path=ROOT / "benchmarks" / "results" / "main_job.json") -> dict[str, dict]:
  """The measurements so far, by CPU model name (``{}`` where none was made).

  A file from before the per-model layout (one flat measurement) reads as that one row.
  """
  path = pathlib.Path(path)
  if not path.exists():
    return {}
  data = json.loads(path.read_text())
  if "runs" in data:
    return data["runs"]
  return {data.get("cpu", "AMD EPYC"): data}


def model_of(cpu: str) -> str:
  """The entry of ``CPU_MODELS`` that ``cpu`` (a model name) belongs to, else ``cpu`` itself."""
  return next((m for m in CPU_MODELS if cpu.startswith(m)), cpu)


def clock_and_cache(row: dict) -> str:
  """A row's CPU clock and cache (``"2596 MHz, cache 1024 KB"``), or ``"not recorded"`` (older rows)."""
  from experiments.provenance import cpu_text
  text = cpu_text({"model": "", "mhz": row.get("cpu_mhz"), "cache": row.get("cpu_cache")}, model=False)
  return text or "not recorded"


def last_cache_line(log: pathlib.Path) -> str | None:
  """The main job's hit-rate line (``XLA compilation cache ...``, its last) in ``log``, or None."""
  try:
    lines = [l.strip() for l in log.read_text(errors="replace").splitlines()]
  except OSError:
    return None
  return next((l for l in reversed(lines) if l.startswith("XLA compilation cache")), None)


def verdicts(times: dict[str, dict], budget_s: float = BUDGET_S) -> tuple[list[str], bool]:
  """Table rows (one per known or measured CPU model) and whether every model meets the budget."""
  rows, ok = [], True
  for model in dict.fromkeys([*CPU_MODELS, *(model_of(c) for c in times)]):
    mine = {c: t for c, t in times.items() if model_of(c) == model}
    if not mine:
      rows.append(f"| {model} | | not measured yet | | | | | **not shown** |")
      ok = False
      continue
    for cpu, t in mine.items():
      within = t["main_job_s"] <= budget_s
      ok &= within
      rows.append(f"| {cpu} | {clock_and_cache(t)} | {t['commit']} | {t['date'][:10]} | {t['install_s']:.0f} s | "
                  f"{t['main_job_s']:.0f} s = {t['main_job_s'] / 60:.1f} min | {t['load_before']} / "
                  f"{t['load_after']} | {'within' if within else '**OVER**'} |")
  return rows, ok


def read_phases(path: pathlib.Path) -> dict:
  """``{"phases_s": {...}, "other_s": ...}`` of the job's ``results/phases.json``, or ``{}`` where the
  commit run predates it."""
  if not path.is_file():
    return {}
  record = json.loads(path.read_text())
  return {"phases_s": record["phases_s"], "other_s": record["other_s"]}


def phase_table(times: dict[str, dict]) -> list[str]:
  """Markdown lines: where each CPU model's latest main job spent its wall time (``[]`` if no row has phases)."""
  timed = {cpu: t for cpu, t in times.items() if "phases_s" in t}
  if not timed:
    return []
  names = list(dict.fromkeys(n for t in timed.values() for n in t["phases_s"]))
  lines = ["Where the job's time went (its `results/phases.json`: wall seconds of each step, in the"
           " order they ran; *other* is imports, startup and what lies between the steps):", "",
           "| CPU | commit | " + " | ".join(names) + " | other |",
           "|---|---|" + "---:|" * (len(names) + 1)]
  for cpu, t in timed.items():
    cells = [f"{t['phases_s'][n]:.0f}" if n in t["phases_s"] else "—" for n in names]
    lines.append(f"| {model_of(cpu)} | {t['commit']} | " + " | ".join(cells) + f" | {t['other_s']:.0f} |")
  return lines + [""]


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--out", default="benchmarks/results/main_job.md")
  parser.add_argument("--keep", default=None, help="clone into DIR and keep it (default: a temporary folder)")
  args = parser.parse_args(argv)
  from experiments.provenance import cpu_facts, cpu_model, git_commit, load_average, provenance
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
  # A newcomer's clone compiles from an empty cache: the clone's own .cache/xla, not one named here.
  env = {k: v for k, v in os.environ.items()
         if k not in ("PYTHONPATH", "VIRTUAL_ENV", "NLOSJAX_CACHE_DIR", "NLOSJAX_CACHE", "JAX_COMPILATION_CACHE_DIR")}
  env["PATH"] = f"{venv / 'bin'}:{env.get('PATH', '')}"
  env["VIRTUAL_ENV"] = str(venv)
  print(f"main job: installing and running `{COMMAND}` in {clone} (log: {log})", flush=True)
  install_s = _run("pip install -q -e .", clone, env, log)
  job_s = _run("python -m experiments.train", clone, env, log)
  table = (clone / "runs" / "default" / "results" / "table.md").read_text()
  load_after = load_average(", ")
  out = pathlib.Path(args.out)
  out.parent.mkdir(parents=True, exist_ok=True)
  times = read_times(out.with_suffix(".json"))
  cpu = cpu_facts()
  times[cpu_model()] = {"commit": commit, "date": date, "install_s": round(install_s, 1),
                        "main_job_s": round(job_s, 1), "budget_s": BUDGET_S, "load_before": load_before,
                        "load_after": load_after, "cpu_mhz": cpu["mhz"], "cpu_cache": cpu["cache"],
                        "compilation_cache": last_cache_line(log),
                        **read_phases(clone / "runs" / "default" / "results" / "phases.json")}
  rows, ok = verdicts(times)
  lines = ["# The main job from a fresh clone, on each CPU model", ""] + facts + [
      f"- Load average before the clone: {load_before}; after the job: {load_after}", "",
      f"README command 1, `{COMMAND}`, in a fresh clone of the commit named in each row and a fresh "
      "virtual environment (the install, downloads included, resolves the newest versions "
      "`pyproject.toml` allows). Each CPU model's row is its latest run of this command; a row "
      "at an older commit than the one above measured older code.", "",
      "| CPU | clock, cache | commit | date | `pip install -e .` | `python -m experiments.train` | "
      f"load before / after | budget {BUDGET_S} s |", "|---|---|---|---|---|---|---|---|", *rows, "",
      f"This run's compilation cache (empty at the start): {times[cpu_model()]['compilation_cache'] or 'no line'}.",
      "", *phase_table(times),
      f"The main job is **{'within' if ok else 'not shown to be within'}** its budget of {BUDGET_S} s "
      f"(20 min on 2 cores) on every CPU model ({', '.join(CPU_MODELS)}).", "",
      f"## The main job's table from this run ({cpu_model()}; `runs/default/results/table.md`, 1 training seed)",
      "", table]
  out.write_text("\n".join(lines))
  out.with_suffix(".json").write_text(json.dumps({"budget_s": BUDGET_S, "runs": times}, indent=2) + "\n")
  if tmp is not None:
    tmp.cleanup()
  print(out.read_text())


if __name__ == "__main__":
  main()
