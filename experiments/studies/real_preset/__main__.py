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
  parser.add_argument("--candidates", action="store_true",
                      help="when the runs are done: make one workdir per candidate in the store and print "
                           "the experiments.studies.preset_choice command that compares them with the shipped weights")
  parser.add_argument("--align", nargs="*", default=None, metavar="NAME",
                      help="run the alignment stage instead of training (default all: "
                           f"{' '.join(a.name for a in study.ALIGNMENTS)})")
  parser.add_argument("--data-dir", default=None, help="folder of measured .mat scans (as experiments.studies.align's)")
  args = parser.parse_args(argv)
  if args.candidates:
    from nlosjax.evaluation.baselines import CLASSIC_METHODS
    models = ["--model shipped=pretrained:real"]
    for config in dict.fromkeys(r.config for r in study.RUNS):
      models.append(f"--model {pathlib.Path(config).stem}={study.candidate_workdir(config)}")
    print("python -m experiments.studies.preset_choice " + " ".join(models)
          + f" --methods {' '.join(CLASSIC_METHODS)}"
          + " --out experiments/studies/preset_choice/results/preset_choice_real.md")
    return 0
  if args.hours is not None and not args.hours > 0:
    parser.error(f"--hours must be > 0, got {args.hours}")
  try:
    runs = study.select(args.runs)
  except ValueError as e:
    parser.error(str(e))
  from experiments.studies.real_undersampling import default_files, scene_name
  files = default_files(args.data_dir)
  if not args.status:
    from experiments import xla_cache
    xla_cache.enable(tidy=True)
    if args.align is not None:
      try:
        study.run_alignments(files, args.align, hours=args.hours)
      except ValueError as e:
        parser.error(str(e))
    else:
      study.run_study([r.name for r in runs], hours=args.hours, allow_data_change=args.allow_data_change)
  print(study.format_status([study.status(r) for r in study.RUNS]))
  scenes = [scene_name(pathlib.Path(f)) for f in files]
  print()
  print(study.format_alignment_status([study.alignment_status(a, scenes) for a in study.ALIGNMENTS]))
  return 0


if __name__ == "__main__":
  sys.exit(main())
