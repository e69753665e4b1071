"""``python -m experiments.studies.physics_shift``: the study's command line."""

from __future__ import annotations

import pathlib
import sys
import time

from experiments.studies import physics_shift
from experiments.studies.physics_shift import heldout, report, study


def main(argv=None) -> int:
  from experiments.cli import config_parser, parse_config
  from experiments.provenance import provenance
  from experiments.studies.mechanisms import STUDY_STOP, code_at_start, study_optim, study_recipe
  code_at_start()
  parser = config_parser(physics_shift.__doc__.split("\n\n")[0])
  parser.add_argument("--designs", nargs="+", choices=list(study.DESIGNS), default=list(study.DESIGNS))
  parser.add_argument("--variants", nargs="+", choices=list(study.VARIANTS), default=list(study.VARIANTS))
  parser.add_argument("--conditions", nargs="+", choices=list(heldout.CONDITIONS),
                      default=list(heldout.CONDITIONS), help="held-out renderer conditions")
  parser.add_argument("--max-runs", type=int, default=None, help="train at most this many runs")
  parser.add_argument("--time-limit-s", type=float, default=None,
                      help="start no run after this many seconds (a started run finishes)")
  parser.add_argument("--workdir", default="runs/physics_shift", help="run folders")
  parser.add_argument("--results", default=str(pathlib.Path(__file__).resolve().parent / "results"),
                      help="JSON files and report (default: this study's results folder)")
  parser.add_argument("--report-only", action="store_true", help="only rewrite the report from the JSON files")
  parser.add_argument("--state", default=None, metavar="DIR",
                      help="export each run's resumable state to DIR/<design>-<variant> at every checkpoint "
                           "and resume from it (commit DIR: a fresh clone continues the run)")
  parser.add_argument("--hours", type=float, default=None,
                      help="with --state: pause the run in progress after this many hours, its state exported")
  argv = sys.argv[1:] if argv is None else list(argv)
  args, base, overrides = parse_config(parser, argv)
  base = study_recipe(base, overrides)      # the mechanism study's runs' model and loss
  base.setdefault("train", {})["optim"] = study_optim(base, overrides)   # the mechanism study's runs' schedule
  if args.hours is not None and args.state is None:
    parser.error("--hours needs --state DIR (where the paused state goes)")
  preset = args.config
  results, workdir = pathlib.Path(args.results), pathlib.Path(args.workdir)
  stop = {**STUDY_STOP, **base.get("train", {}).get("stop", {})}
  physics = base["data"].get("physics")
  if not args.report_only:
    from tqdm import tqdm

    from nlosjax.train import TrainingPaused
    sets = study.test_sets(base, args.conditions, physics)
    jobs = [("classic", study.classic_design(name), name) for name in study.scored_by_classic(sets)]
    jobs += [("run", d, v) for d in args.designs for v in args.variants]
    done = {j for j in jobs if (study.classic_path(results, j[1], j[2]).exists() if j[0] == "classic"
                                else not study.incomplete(results, j[1], j[2], sets))}
    todo = [j for j in jobs if j not in done]
    print(f"physics_shift: {len(done)} of {len(jobs)} records exist in {results / 'physics_shift'}; "
          f"{len(todo)} to do")
    t0, trained = time.perf_counter(), 0
    deadline = None if args.hours is None else time.time() + 3600 * args.hours
    state = None if args.state is None else pathlib.Path(args.state)
    for kind, a, b in tqdm(todo, desc="physics_shift", unit="job"):
      if kind == "classic":
        study.run_classic(base, a, b, sets, results, preset, physics, log=tqdm.write)
        continue
      if args.max_runs is not None and trained >= args.max_runs:
        tqdm.write(f"physics_shift: --max-runs {args.max_runs} reached")
        break
      if args.time_limit_s is not None and time.perf_counter() - t0 > args.time_limit_s:
        tqdm.write(f"physics_shift: --time-limit-s {args.time_limit_s:g} passed; no new run starts")
        break
      new = not study.run_path(results, a, b).exists()
      try:
        study.run_design(base, a, b, sets, stop, workdir, results, preset, physics, log=tqdm.write,
                         state=state, deadline=deadline)
      except TrainingPaused as e:
        tqdm.write(f"physics_shift: {a}-{b} {e}; the same command continues it")
        break
      trained += new
  runs, classic = report.load(results)
  command = "python -m experiments.studies.physics_shift " + " ".join(argv)
  text = report.to_markdown(runs, classic, provenance(command.strip()), args.conditions)
  out = results / "physics_shift.md"
  out.write_text(text)
  report.plot(runs, classic, args.conditions, results / "physics_shift.png")
  print(text)
  return 0


if __name__ == "__main__":
  sys.exit(main())
