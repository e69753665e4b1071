"""Time to the validation plateau: the study's schedule against a shorter, hotter one (issue 62).

    python -m benchmarks.time_to_plateau [--rows full ours_s] [--seeds 0 1 2]
                                         [--workdir runs/time_to_plateau] [--results benchmarks/results]
                                         [--report-only]

The mechanism study (:mod:`benchmarks.mechanisms`) trains each row of the ``cpu`` preset to its
validation plateau: peak learning rate 1e-3, a cosine schedule over 3000 steps, the plateau rule
(:data:`benchmarks.mechanisms.design.STUDY_STOP`). Its records at the preset's photons
(``RESULTS/mechanisms/full/<row>-seed<s>.json``) are this comparison's ``study`` side. The
``short`` side (:data:`SHORT`) trains the same row from the same seed on the same data, model,
loss, stopping rule and evaluation, changing two numbers: the peak learning rate and the cosine
horizon (the most steps). Records: ``RESULTS/time_to_plateau/<row>-seed<s>.json``, the study's
record format; the report: ``RESULTS/time_to_plateau.md``.

Time: both sides run the same train step and the same validation (one per 50 steps), so their
time to the plateau is in proportion to the steps taken; with a fixed seed the steps are the same
on any machine, and their ratio is the time ratio. Each record's wall time is shown with its
machine, not compared across machines. Accuracy: each seed's test scores paired with the same
seed's study run on the same frames, ``short - study``, with the bootstrap interval over
sequences and seeds (:func:`nlosjax.evaluation.scores.compare_scores`).
"""

from __future__ import annotations

import pathlib
import sys

import numpy as np

from benchmarks.mechanisms.design import COLUMNS, ROWS, STUDY_OPTIM, STUDY_STOP, run_config, run_dir, study_optim
from benchmarks.mechanisms.records import _array, load_runs, write_json
from benchmarks.mechanisms.report import same_frames, stack_scores

#: The short schedule: peak learning rate and cosine horizon (= the most steps); all else the study's.
SHORT = {"learning_rate": 3e-3, "max_steps": 400}
BUDGET = "full"
NAME = "time_to_plateau"
DEFAULT_ROWS = ("full", "ours_s")


def short_config(base: dict, row: str, seed: int) -> dict:
  """The study's run config of ``row``/``seed`` at the preset's photons, with :data:`SHORT`'s two numbers."""
  cfg = run_config(base, BUDGET, row, seed, {**STUDY_STOP, "max_steps": SHORT["max_steps"]})
  cfg["train"]["optim"] = {**cfg["train"]["optim"], "learning_rate": SHORT["learning_rate"]}
  return cfg


def record_path(results: pathlib.Path, row: str, seed: int) -> pathlib.Path:
  return pathlib.Path(results) / NAME / f"{row}-seed{seed}.json"


def run_short(base: dict, row: str, seed: int, workdir: pathlib.Path, results: pathlib.Path) -> dict:
  """Train (or reload) one short-schedule run, score it on test; writes and returns its record."""
  from benchmarks.mechanisms.study import run_record, train_and_score
  from nlosjax import train as T
  cfg = short_config(base, row, seed)
  data_path = pathlib.Path(cfg["data"]["path"])
  T.ensure_dataset(cfg, data_path)
  folder = run_dir(workdir, BUDGET, row, seed)
  folder.mkdir(parents=True, exist_ok=True)
  _, _, test = train_and_score(cfg, folder, ROWS[row][1], print)
  record = {**run_record(cfg, BUDGET, row, seed, folder, test), "schedule": dict(SHORT)}
  write_json(record_path(results, row, seed), record)
  return record


def _mean(r: dict, metric: str) -> float:
  return float(np.nanmean(_array(r["test"]["scores"][metric])))


def report(study: dict, short: dict, command: str) -> str:
  """The markdown report of ``(row, seed) -> record`` of both sides."""
  from experiments import provenance
  from nlosjax.evaluation import scores
  from nlosjax.stats import format_interval as cell
  lines = ["# Time to the validation plateau: the study's schedule against a short one", ""]
  lines += provenance.provenance(command) + [""]
  lines += [f"`cpu` preset at its photons, each row trained until learning stops (plateau rule every "
            f"{STUDY_STOP['every']} steps, patience {STUDY_STOP['patience']}, {STUDY_STOP['min_delta_db']} dB) or "
            f"at the schedule's horizon. **study**: peak learning rate {STUDY_OPTIM['learning_rate']:g}, "
            f"cosine over {STUDY_STOP['max_steps']} "
            f"steps (`RESULTS/mechanisms/full/`). **short**: peak {SHORT['learning_rate']:g}, cosine over "
            f"{SHORT['max_steps']} steps. Same data, model, loss, seed, stopping rule and evaluation; both sides run "
            "the same step and validation, so the ratio of steps taken is the ratio of time on any machine.", "",
            "| row | seed | steps: study → short (ratio) | best step | validation PSNR (dB): study → short "
            "| test PSNR (dB): study → short | train wall s: study / short (their machines) |",
            "|---|---|---|---|---|---|---|"]
  rows = sorted({k[0] for k in short})
  for row, seed in sorted(short):
    a, b = study.get((row, seed)), short[(row, seed)]
    if a is None:
      lines.append(f"| {row} | {seed} | — → {b['steps_taken']} | {b['best_step']} | — → {b['best_val_psnr']:.2f} "
                   f"| — → {_mean(b, 'psnr'):.2f} | — / {b['train_wall_s']:.0f} |")
      continue
    steps = f"{a['steps_taken']} → {b['steps_taken']} ({b['steps_taken'] / a['steps_taken']:.2f})"
    lines.append(f"| {row} | {seed} | {steps} "
                 f"| {a['best_step']} → {b['best_step']} | {a['best_val_psnr']:.2f} → {b['best_val_psnr']:.2f} "
                 f"| {_mean(a, 'psnr'):.2f} → {_mean(b, 'psnr'):.2f} "
                 f"| {a['train_wall_s']:.0f} ({a['machine'].get('cpu', '?')}) / {b['train_wall_s']:.0f} "
                 f"({b['machine'].get('cpu', '?')}) |")
  lines += ["", "Paired on the same test frames and seeds, short − study (mean [95 % interval over sequences "
            "and seeds]); called where the interval excludes 0:", "",
            "| row | seeds | steps ratio (sum) | " + " | ".join(h for h, _ in COLUMNS.values()) + " |",
            "|---|---|---|" + "---|" * len(COLUMNS)]
  verdicts = []
  for row in rows:
    seeds = sorted(s for (r, s) in short if r == row and (r, s) in study)
    if not seeds:
      continue
    a = [study[(row, s)] for s in seeds]
    b = [short[(row, s)] for s in seeds]
    if not same_frames(a + b):
      raise ValueError(f"{row}: the runs were scored on different test frames")
    diff = scores.compare_scores({m: stack_scores(b, m) for m in COLUMNS},
                                 {m: stack_scores(a, m) for m in COLUMNS}, a[0]["test"]["sequence"])
    ratio = sum(r["steps_taken"] for r in b) / sum(r["steps_taken"] for r in a)
    lines.append(f"| {row} | {', '.join(map(str, seeds))} | {ratio:.2f} | "
                 + " | ".join(cell(diff[m], d, signed=True) for m, (_, d) in COLUMNS.items()) + " |")
    lo, hi = diff["psnr"]["ci95"]
    verdicts.append(f"- {row}: {ratio:.2f}x the steps (goal ≤ 0.50); test PSNR short − study "
                    f"{cell(diff['psnr'], 2, signed=True)} dB, "
                    + ("not called (the interval holds 0)." if lo <= 0 <= hi else
                       ("higher (called)." if lo > 0 else "lower (called).")))
  lines += ["", *verdicts]
  return "\n".join(lines) + "\n"


def load_short(results: pathlib.Path) -> dict:
  import json
  out = {}
  for path in sorted((pathlib.Path(results) / NAME).glob("*-seed*.json")):
    r = json.loads(path.read_text())
    out[(r["row"], int(r["seed"]))] = r
  return out


def main(argv=None) -> int:
  from experiments.cli import config_parser, parse_config
  parser = config_parser(__doc__.split("\n\n")[0])
  parser.add_argument("--rows", nargs="+", choices=list(ROWS), default=list(DEFAULT_ROWS))
  parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
  parser.add_argument("--workdir", default=f"runs/{NAME}")
  parser.add_argument("--results", default=str(pathlib.Path(__file__).resolve().parent / "results"))
  parser.add_argument("--report-only", action="store_true")
  args, base, overrides = parse_config(parser, argv)
  from benchmarks.mechanisms.records import code_at_start
  from nlosjax.train import with_defaults
  code_at_start()                          # the commit and code this process loads, for the records
  base = with_defaults(base)
  base["train"]["optim"] = study_optim(base, overrides)   # the study side's, as benchmarks.mechanisms runs it
  results = pathlib.Path(args.results)
  if not args.report_only:
    for row in args.rows:
      for seed in args.seeds:
        if record_path(results, row, seed).exists():
          print(f"{NAME}: {record_path(results, row, seed)} exists; delete it to run again")
          continue
        run_short(base, row, seed, pathlib.Path(args.workdir), results)
  study = {k[1:]: r for k, r in load_runs(results).items() if k[0] == BUDGET}
  short = load_short(results)
  if not short:
    raise SystemExit(f"{NAME}: no short-schedule record under {results / NAME}")
  command = "python -m benchmarks.time_to_plateau " + " ".join(sys.argv[1:] if argv is None else argv)
  text = report(study, short, command.strip())
  (results / f"{NAME}.md").write_text(text)
  print(text)
  return 0


if __name__ == "__main__":
  sys.exit(main())
