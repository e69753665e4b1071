"""``python -m experiments.studies.headroom``: the study's command line."""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

from experiments.studies import headroom
from experiments.studies.headroom import report, study

SETS = ("test", "independent", "heldout")


def parse_models(items, defaults) -> dict:
  """``--model LABEL=RUN`` items -> ``label -> RUN`` over ``defaults`` (a label of theirs is replaced)."""
  models = dict(defaults)
  seen = set()
  for item in items or ():
    name, sep, spec = item.partition("=")
    if not sep or not name or not spec:
      raise SystemExit(f"--model takes LABEL=RUN, got {item!r}")
    if name in seen:
      raise SystemExit(f"--model: label {name!r} given twice")
    if name in (study.ZERO, *study.TRUTH, *study.CLASSIC) or name.startswith("reference") or "@" in name:
      raise SystemExit(f"--model: label {name!r} names one of the study's own rows")
    seen.add(name)
    models[name] = spec
  return models


def main(argv=None) -> int:
  from experiments.studies.physics_shift.heldout import CONDITIONS
  parser = argparse.ArgumentParser(description=headroom.__doc__.split("\n\n")[0])
  parser.add_argument("--model", action="append", metavar="LABEL=RUN",
                      help="a finished study run folder or pretrained:NAME/VARIANT (repeatable), beside the "
                           "shipped cpu networks")
  parser.add_argument("--sets", nargs="+", choices=SETS, default=list(SETS))
  parser.add_argument("--conditions", nargs="+", choices=CONDITIONS, default=list(study.HELDOUT_CONDITIONS),
                      help="the held-out renderer's conditions")
  parser.add_argument("--methods", nargs="+", choices=study.CLASSIC, default=list(study.CLASSIC),
                      help="the classic methods")
  parser.add_argument("--results", default=str(headroom.RESULTS), help="report and records (default: this "
                      "study's results folder)")
  parser.add_argument("--report-only", action="store_true", help="only rebuild the report from the records")
  parser.add_argument("--tiny", action="store_true",
                      help="the tiny run's data (files under --results), no network unless --model names one")
  argv = sys.argv[1:] if argv is None else list(argv)
  args = parser.parse_args(argv)
  from experiments.provenance import provenance
  from experiments.studies.mechanisms import code_at_start
  code_at_start()          # the records name the commit this process started from, not a later one
  t0 = time.perf_counter()
  results = pathlib.Path(args.results)
  cfg = study.preset(results / "data" if args.tiny else None)
  models = parse_models(args.model, {} if args.tiny else study.DEFAULT_MODELS)
  if not args.report_only:
    files = study.set_files(cfg, args.sets, args.conditions, tiny=args.tiny)
    run = study.Study(cfg, results, models, args.methods)
    val_path, _ = files["val"]
    choices = run.choices(val_path)
    run.score_set("val", val_path, "val", choices, learned=False)
    val = study.load_records(results)["sets"]["val"]["methods"]
    run.reference(val)
    run.oracle_choices(val_path)
    choices = json.loads((results / "headroom" / "choices.json").read_text())
    for name, (path, split) in files.items():
      if name != "val":
        run.score_set(name, path, split, choices)
    run.log_invocation(" ".join(argv), time.perf_counter() - t0)
  records = study.load_records(results)
  summary = report.summarise(records)
  command = "python -m experiments.studies.headroom " + " ".join(argv)
  text = report.to_markdown(summary, provenance(command.strip()), records["choices"],
                            stride=int(cfg["data"]["input_stride"]), grid=_grid(cfg["data"]["grid"]),
                            invocations=records["invocations"])
  (results / "headroom.md").write_text(text)
  from experiments.studies.mechanisms import write_json
  write_json(results / "headroom.json", summary)
  report.plot(summary, results / "headroom.png")
  print(text)
  return 0


def _grid(grid):
  return (int(grid), int(grid)) if not isinstance(grid, (list, tuple)) else tuple(int(g) for g in grid)


if __name__ == "__main__":
  sys.exit(main())
