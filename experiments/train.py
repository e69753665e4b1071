"""The main job: make the dataset if absent, train Ours-S and Ours, evaluate against the classic methods.

Usage::

  python -m experiments.train                               # CPU preset, runs/default
  python -m experiments.train --config paper --workdir runs/paper   # paper scale (GPU)
  python -m experiments.train --config.train.steps=50 --config.train.seed=1
  python -m experiments.train --config.data.renderer=lct --config.data.retroreflective=0.0
  python -m experiments.train --seeds 3 --workdir runs/seeds3   # Table 1 over 3 training seeds
  python -m experiments.train --config paper --dry-run      # memory and time, nothing trained
  # a long run: state mirrored into a folder to commit, resumed from it on a fresh clone,
  # paused cleanly after 2 hours (exit status 75; the same command continues it)
  python -m experiments.train --config real --workdir ~/.cache/nlosjax/runs/real \
      --resume-from experiments/studies/real_preset/state/real --hours 2
  # several hosts (or processes): the same command on each, process ids 0 .. N-1
  python -m experiments.train --config paper --coordinator host0:1234 --num-processes N --process-id I

Every choice (classic settings, checkpoints) is made on the validation split;
the test split only writes the tables. Where the config has an ``independent``
section (the CPU preset does), the models are also scored on an independent
test set (:mod:`experiments.independent_set`: other shapes, motion, renderer
and noise code) into ``results/table1_independent.md``. Writes ``WORKDIR/results/{table.md,
table.json, comparisons.json, validation.json, comparison.png,
training_curves.png}`` (see :mod:`experiments.main_job`); rerun the same command after an interruption to
resume from the last checkpoint.

``--dry-run`` builds the data spec, model and optimiser, compiles the train
and inference steps from shapes, prints per device the planned peak memory,
FLOPs and an estimated time per step and for the run (measured at a reduced
size, :mod:`nlosjax.plan`), and exits without generating data. With several
processes each one reads only its rows of every global batch; process 0 makes
the dataset (on a file system the others see), writes the logs and evaluates.

``--config`` (a preset's name or a file whose ``get_config()`` returns an
``ml_collections.ConfigDict``) and the ``--config.section.key=value`` overrides
are read by ``ml_collections.config_flags`` (:mod:`experiments.cli`), as in
``python -m experiments.make_dataset``: with the same ``--config`` and
``--config.data.*`` overrides it writes the dataset file this command would
make for itself. The config is locked: an unknown key or a value of the wrong
type exits with one line naming it, before any data is made or model trained.
The typed :class:`~nlosjax.train.RunConfig` is built from it once, here.

Compiled programs are kept in the clone's persistent XLA compilation cache
(``.cache/xla``; ``NLOSJAX_CACHE_DIR`` names another folder, ``NLOSJAX_CACHE=0``
switches it off; :mod:`experiments.xla_cache`), so a rerun reads what an earlier
run compiled; the last line printed is the cache's hit rate.
"""

from experiments.cli import config_parser, one_line_errors, parse_config

#: Exit status of a run paused at its ``--hours`` deadline (``EX_TEMPFAIL``: run the same command again).
EXIT_PAUSED = 75
#: One JSON line per invocation of this command on a workdir (experiments.provenance.run_record).
INVOCATIONS = "invocations.jsonl"


def record_invocation(workdir, argv=None) -> dict:
  """Append where and from which commit this process trains to ``<workdir>/invocations.jsonl``.

  A resumed run adds a line, so the file says every commit and machine the
  run's steps came from; ``experiments.export_weights`` records them with the
  weights. Returns the record written.
  """
  import json
  import pathlib
  import shlex
  import sys

  from experiments.provenance import run_record
  argv = sys.argv[1:] if argv is None else list(argv)
  record = run_record(" ".join(["python -m experiments.train", *map(shlex.quote, argv)]))
  from nlosjax.files import writing
  workdir = pathlib.Path(workdir)
  path = workdir / INVOCATIONS
  with writing(path):
    workdir.mkdir(parents=True, exist_ok=True)
    cut = path.is_file() and path.stat().st_size and not path.read_bytes().endswith(b"\n")
    with open(path, "a") as f:
      f.write(("\n" if cut else "") + json.dumps(record) + "\n")   # after a line a kill cut short
  return record


def main(argv=None):
  parser = config_parser(__doc__.split("\n\n")[0])
  parser.add_argument("--workdir", default="runs/default", help="output folder")
  parser.add_argument("--seeds", type=int, default=None,
                      help="training seeds per variant (default: the config's train.seeds, 1); "
                           "tables then cover seeds too")
  parser.add_argument("--dry-run", action="store_true",
                      help="predict memory and time per device, then exit (no data, no training)")
  parser.add_argument("--no-measure", action="store_true",
                      help="with --dry-run: compile only, no timed steps at a reduced size")
  parser.add_argument("--resume-from", default=None, metavar="DIR",
                      help="mirror each model's resumable state into DIR at every checkpoint and "
                           "resume from it where it is ahead of --workdir (commit DIR to continue "
                           "on a fresh clone)")
  parser.add_argument("--hours", type=float, default=None,
                      help="pause training after this many hours (state exported; exit status 75)")
  parser.add_argument("--allow-data-change", action="store_true",
                      help="with --resume-from: resume on data that differ beyond float rounding "
                           "(data regenerated on another CPU model are taken without it when their "
                           "fingerprint agrees)")
  parser.add_argument("--coordinator", default=None,
                      help="host:port of process 0 for multi-process training (jax.distributed)")
  parser.add_argument("--num-processes", type=int, default=1, help="processes in all (default 1)")
  parser.add_argument("--process-id", type=int, default=0, help="this process, 0 .. N-1")
  from experiments import xla_cache
  xla_cache.add_argument(parser)
  args, config, _ = parse_config(parser, argv)
  xla_cache.enable_unless(args.no_cache, tidy=True)        # before anything compiles
  from nlosjax.train import TrainingPaused
  try:
    with one_line_errors():          # a bad or damaged input, a full disk: one line, exit status 2
      run(args, config, parser, argv)
  except TrainingPaused as e:
    print(f"{e}; rerun the same command to continue", flush=True)
    print(xla_cache.summary(), flush=True)
    raise SystemExit(EXIT_PAUSED) from None
  print(xla_cache.summary(), flush=True)


def run(args, config, parser, argv=None):
  """The main job once its arguments are parsed (``--dry-run``: the plan only)."""
  if args.seeds is not None:
    if args.seeds < 1:
      parser.error(f"--seeds must be >= 1, got {args.seeds}")
    config.setdefault("train", {})["seeds"] = args.seeds
  from nlosjax.train import RunConfig
  try:
    config = RunConfig.from_dict(config)        # typed and frozen from here on
    config.data.spec()                          # every data value checked before any work
  except (TypeError, ValueError) as e:
    raise SystemExit(f"--config {args.config}: {e}") from None
  independent = config.extra.get("independent")
  if independent and "path" not in independent:
    raise SystemExit(f"--config {args.config}: independent.path is needed where the independent set is set")
  if args.num_processes > 1:
    if not args.coordinator:
      parser.error("--num-processes > 1 needs --coordinator host:port (process 0's address)")
    from nlosjax.train import initialize_distributed
    initialize_distributed(args.coordinator, args.num_processes, args.process_id)
  if args.hours is not None and not args.hours > 0:
    parser.error(f"--hours must be > 0, got {args.hours}")
  if (args.hours is not None or args.allow_data_change) and not args.resume_from:
    parser.error("--hours and --allow-data-change need --resume-from DIR (where the paused state goes)")
  if args.dry_run:
    from nlosjax.plan import dry_run, format_plan
    print(format_plan(dry_run(config, measure=not args.no_measure)))
    return
  from experiments.main_job import train_and_evaluate
  if args.process_id == 0:
    record_invocation(args.workdir, argv)
  extra = {}
  if independent:
    from experiments.independent_set import ensure_independent_set
    extra["independent"] = ensure_independent_set(
        independent["path"], dict(config.data.section), independent.get("sequences", 8),
        independent.get("frames", 8), independent.get("seed", 2026))
  kwargs = {"extra_test_sets": extra} if extra else {}
  if args.resume_from:
    kwargs["export"] = _state_export(args)
  train_and_evaluate(config, args.workdir, **kwargs)


def _state_export(args):
  """The run's :class:`~nlosjax.train.StateExport` of ``--resume-from``, ``--hours``, ``--allow-data-change``.

  The export folder also gets this invocation's line (``invocations.jsonl``), so a
  committed state says every commit and machine its steps came from.
  """
  import json
  import pathlib
  import time

  from nlosjax.files import writing
  from nlosjax.train import StateExport
  folder = pathlib.Path(args.resume_from)
  if args.process_id == 0:
    line = (pathlib.Path(args.workdir) / INVOCATIONS).read_text().splitlines()[-1]
    path = folder / INVOCATIONS
    with writing(path):
      folder.mkdir(parents=True, exist_ok=True)
      cut = path.is_file() and path.stat().st_size and not path.read_bytes().endswith(b"\n")
      with open(path, "a") as f:
        f.write(("\n" if cut else "") + json.dumps({**json.loads(line), "workdir": str(args.workdir)}) + "\n")
  return StateExport(folder, deadline=None if args.hours is None else time.time() + 3600 * args.hours,
                     allow_data_change=args.allow_data_change)


if __name__ == "__main__":
  main()
