"""The main job: make the dataset if absent, train Ours-S and Ours, evaluate against the classic methods.

Usage::

  python -m experiments.train                               # CPU preset, runs/default
  python -m experiments.train --config paper --workdir runs/paper   # paper scale (GPU)
  python -m experiments.train --config.train.steps=50 --config.train.seed=1

Writes ``WORKDIR/results/{table.md, table.json, comparison.png,
training_curves.png}``; rerun the same command after an interruption to
resume from the last checkpoint.
"""

import argparse

from experiments.cli import apply_overrides, load_config


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--config", default="cpu", help="preset name (cpu, paper) or a .py file")
  parser.add_argument("--workdir", default="runs/default", help="output folder")
  args, overrides = parser.parse_known_args(argv)
  config = apply_overrides(load_config(args.config), overrides)
  from nlosjax.train import train_and_evaluate
  train_and_evaluate(config, args.workdir)


if __name__ == "__main__":
  main()
