"""The main job: make the dataset if absent, train Ours-S and Ours, evaluate against the classic methods.

Usage::

  python -m experiments.train                               # CPU preset, runs/default
  python -m experiments.train --config paper --workdir runs/paper   # paper scale (GPU)
  python -m experiments.train --config.train.steps=50 --config.train.seed=1
  python -m experiments.train --seeds 3 --workdir runs/seeds3   # Table 1 over 3 training seeds

Every choice (classic settings, checkpoints) is made on the validation split;
the test split only writes the tables. Where the config has an ``independent``
section (the CPU preset does), the models are also scored on an independent
test set (:mod:`experiments.independent_set`: other shapes, motion, renderer
and noise code) into ``results/table1_independent.md``. Writes ``WORKDIR/results/{table.md,
table.json, comparisons.json, validation.json, comparison.png,
training_curves.png}`` (see :mod:`nlosjax.main_job`); rerun the same command after an interruption to
resume from the last checkpoint.
"""

import argparse

from experiments.cli import apply_overrides, load_config


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--config", default="cpu", help="preset name (cpu, paper) or a .py file")
  parser.add_argument("--workdir", default="runs/default", help="output folder")
  parser.add_argument("--seeds", type=int, default=None,
                      help="training seeds per variant (default: the config's train.seeds, 1); "
                           "tables then cover seeds too")
  args, overrides = parser.parse_known_args(argv)
  config = apply_overrides(load_config(args.config), overrides)
  if args.seeds is not None:
    if args.seeds < 1:
      parser.error(f"--seeds must be >= 1, got {args.seeds}")
    config.setdefault("train", {})["seeds"] = args.seeds
  from nlosjax.main_job import train_and_evaluate
  extra = {}
  spec = config.get("independent")
  if spec:
    from experiments.independent_set import ensure_independent_set
    extra["independent"] = ensure_independent_set(
        spec["path"], config["data"], spec.get("sequences", 8), spec.get("frames", 8),
        spec.get("seed", 2026))
  train_and_evaluate(config, args.workdir, **({"extra_test_sets": extra} if extra else {}))


if __name__ == "__main__":
  main()
