"""``python -m experiments.studies.real_preset``: the package docstring says how."""

import argparse
import pathlib
import sys

from experiments.studies import real_preset
from experiments.studies.real_preset import study


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=real_preset.__doc__.split("\n\n")[0],
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--status", action="store_true", help="print what the committed state says; train nothing")
  parser.add_argument("--runs", nargs="+", default=None, help=f"runs to train (default all: "
                      f"{' '.join(r.name for r in study.RUNS)})")
  parser.add_argument("--hours", type=float, default=None, help="pause after this many hours")
  parser.add_argument("--allow-data-change", action="store_true",
                      help="resume even when the regenerated data's content digest differs from the state's")
  parser.add_argument("--choice", metavar="OUT", default=None,
                      help="when the runs are done: python -m benchmarks.preset_choice of the shipped "
                           "real weights against each candidate, beside the classic methods, into OUT")
  args = parser.parse_args(argv)
  if args.choice:
    from benchmarks import preset_choice
    from experiments import xla_cache
    xla_cache.enable(tidy=True)
    models = ["--model", "shipped=pretrained:real"]
    for config in dict.fromkeys(r.config for r in study.RUNS):
      models += ["--model", f"{pathlib.Path(config).stem}={study.candidate_workdir(config)}"]
    return preset_choice.main(models + ["--methods", "fbp", "lct", "fk", "phasor", "rsd", "--out", args.choice])
  if args.hours is not None and not args.hours > 0:
    parser.error(f"--hours must be > 0, got {args.hours}")
  try:
    runs = study.select(args.runs)
  except ValueError as e:
    parser.error(str(e))
  if not args.status:
    from experiments import xla_cache
    xla_cache.enable(tidy=True)
    study.run_study([r.name for r in runs], hours=args.hours, allow_data_change=args.allow_data_change)
  print(study.format_status([study.status(r) for r in study.RUNS]))
  return 0


if __name__ == "__main__":
  sys.exit(main())
