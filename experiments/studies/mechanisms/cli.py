"""``python -m experiments.studies.mechanisms``: the command line (resumable runs, ``--report-only``, ``--tiny``)."""

from __future__ import annotations

import pathlib
import sys
import time

import numpy as np

from experiments.studies.mechanisms.design import (
  BUDGETS,
  EXTRA_ROWS,
  MAIN_ROWS,
  ROWS,
  SEEDS,
  TINY_DESIGN,
  TINY_STOP,
  budget_config,
  check_same_data,
  run_config,
  run_json,
  study_optim,
  study_recipe,
  study_stop,
)
from experiments.studies.mechanisms.records import RESULTS, _array, code_at_start
from experiments.studies.mechanisms.report import write_report
from experiments.studies.mechanisms.study import probe_run_dir, run_one


def tiny_base(workdir: pathlib.Path) -> dict:
  """The tiny config of :mod:`experiments.tiny_run` with its data under ``workdir``."""
  from experiments.tiny_run import tiny_config
  return tiny_config(pathlib.Path(workdir) / "data" / "tiny.h5", stop=dict(TINY_STOP))


def score_untrained_budgets(base: dict, budgets, results: pathlib.Path) -> None:
  """``--untrained``: each budget's JSON of :mod:`experiments.studies.mechanisms.untrained` (kept where present)."""
  from experiments.studies.mechanisms.records import machine, write_json
  from experiments.studies.mechanisms.untrained import score_untrained, untrained_json
  for budget in budgets:
    path = untrained_json(results, budget)
    if path.exists():
      print(f"mechanisms: {path} exists; delete it to score again")
      continue
    record = score_untrained(budget_config(base, budget))
    write_json(path, {"budget": budget, "machine": machine(), **record})
    print(f"mechanisms: wrote {path} ({record['wall_s']:.0f} s)")


def main(argv=None) -> int:
  from experiments.cli import config_parser, parse_config
  code_at_start()                          # before any run: the code this process loads
  parser = config_parser(__doc__.split("\n\n")[0])
  parser.add_argument("--budgets", nargs="+", choices=list(BUDGETS), default=None,
                      help="photon budgets to run (default: all; --tiny: full)")
  parser.add_argument("--rows", nargs="+", choices=list(ROWS), default=None,
                      help=f"rows to run (default: {' '.join(MAIN_ROWS)}, plus --extra-rows)")
  parser.add_argument("--extra-rows", action="store_true", help=f"also run {' and '.join(EXTRA_ROWS)}")
  parser.add_argument("--seeds", nargs="+", type=int, default=None, help="training seeds (default: 0 1 2)")
  parser.add_argument("--max-runs", type=int, default=None, help="train at most this many runs")
  parser.add_argument("--time-limit-s", type=float, default=None,
                      help="start no run after this many seconds (a started run finishes)")
  parser.add_argument("--workdir", default=None, help="run folders (default: runs/mechanisms)")
  parser.add_argument("--results", default=None, help="JSON files and report (default: the study's results folder)")
  parser.add_argument("--report-only", action="store_true", help="only rewrite the report from the JSON files")
  parser.add_argument("--untrained", action="store_true",
                      help="score Table 1's methods without training (the classic five and CSA, tuned on "
                           "validation) on each budget's test frames, then rewrite the report")
  parser.add_argument("--probe", metavar="RUN_DIR", default=None,
                      help="probe the SSMs of a finished run folder, store it in its JSON, rewrite the report")
  parser.add_argument("--tiny", action="store_true", help="the tiny config of experiments/tiny_run.py (a smoke run)")
  parser.add_argument("--state", default=None, metavar="DIR",
                      help="export each run's resumable state to DIR/<budget>/<row>-seed<k> at every "
                           "validation (commit it: a fresh clone resumes from it; e.g. "
                           "experiments/studies/mechanisms/state)")
  parser.add_argument("--hours", type=float, default=None,
                      help="with --state: pause the run in progress after this many hours, its state exported")
  argv = sys.argv[1:] if argv is None else list(argv)
  args, base, overrides = parse_config(parser, argv)
  base = study_recipe(base, overrides)     # the recipe the study's runs were trained with
  if args.hours is not None and not args.state:
    parser.error("--hours needs --state DIR (where the paused state goes)")
  from experiments.cli import override_key
  keep_loss = tuple(k[2] for k in map(override_key, overrides) if k[:2] == ("train", "loss") and len(k) == 3)
  command = "python -m experiments.studies.mechanisms " + " ".join(argv)
  workdir = pathlib.Path(args.workdir or ("runs/mechanisms-tiny" if args.tiny else "runs/mechanisms"))
  results = pathlib.Path(args.results or (workdir / "results" if args.tiny else RESULTS))
  if args.tiny:
    base = tiny_base(workdir)
    design = dict(TINY_DESIGN)
  else:
    stop = study_stop(base)
    base["train"]["stop"] = stop
    base["train"]["optim"] = study_optim(base, overrides)
    design = {"budgets": tuple(BUDGETS), "rows": MAIN_ROWS, "seeds": SEEDS}
  if args.extra_rows:
    design["rows"] = tuple(design["rows"]) + EXTRA_ROWS
  budgets = tuple(args.budgets or design["budgets"])
  rows = tuple(args.rows or design["rows"])
  seeds = tuple(args.seeds if args.seeds is not None else design["seeds"])
  if args.probe:
    probe_run_dir(pathlib.Path(args.probe), results)
  elif args.untrained:
    score_untrained_budgets(base, budgets, results)
  elif not args.report_only:
    from tqdm import tqdm

    from nlosjax.train import TrainingPaused
    stop = dict(base["train"]["stop"])
    jobs = [(b, r, s) for s in seeds for b in budgets for r in rows]
    todo = [j for j in jobs if not run_json(results, *j).exists()]
    print(f"mechanisms: {len(jobs) - len(todo)} of {len(jobs)} runs already have their JSON "
          f"in {results / 'mechanisms'}; {len(todo)} to train")
    for budget, row, seed in todo:
      check_same_data(results, budget,
                      {**run_config(base, budget, row, seed, stop, keep_loss), "_study_row": row})
    t0, trained = time.perf_counter(), 0
    deadline = None if args.hours is None else time.time() + 3600 * args.hours
    state = None if args.state is None else pathlib.Path(args.state)
    for budget, row, seed in tqdm(todo, desc="mechanisms", unit="run"):
      if args.max_runs is not None and trained >= args.max_runs:
        tqdm.write(f"mechanisms: --max-runs {args.max_runs} reached")
        break
      if args.time_limit_s is not None and time.perf_counter() - t0 > args.time_limit_s:
        tqdm.write(f"mechanisms: --time-limit-s {args.time_limit_s:g} passed; no new run starts")
        break
      try:
        rec = run_one(base, budget, row, seed, stop, workdir, results, log=tqdm.write, keep_loss=keep_loss,
                      state=state, deadline=deadline)
      except TrainingPaused as e:
        tqdm.write(f"mechanisms: {budget}/{row}-seed{seed} {e}; the same command continues it")
        break
      trained += 1
      tqdm.write(f"mechanisms: {budget}/{row}-seed{seed}: {rec['steps_taken']} steps "
                 f"({rec['stop_reason']}), best step {rec['best_step']}, test PSNR "
                 f"{np.nanmean(_array(rec['test']['scores']['psnr'])):.2f} dB")
  text = write_report(results, design, command.strip())
  print(text)
  return 0
