"""The dry run of a preset, written to a results file: ``benchmarks/results/dry_run.md``.

    python -m benchmarks.dry_run [--config paper] [--out benchmarks/results/dry_run.md]

Runs :func:`nlosjax.plan.dry_run` (what ``python -m experiments.train --config
paper --dry-run`` prints: XLA's planned peak memory and FLOPs per device for
the train and inference steps, compiled from shapes, and a time per step
extrapolated from steps measured at 1/4 and 1/2 of the grid and bins) and
writes the report with its provenance. On a GPU machine the same command
gives that device's plan and verdict.
"""

from __future__ import annotations

import argparse
import pathlib
import sys

from experiments import provenance as _machine

DEFAULT_OUT = pathlib.Path(__file__).resolve().parent / "results" / "dry_run.md"


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--config", default="paper", help="preset name or .py file (default: %(default)s)")
  parser.add_argument("--out", default=str(DEFAULT_OUT), help="Markdown output")
  args = parser.parse_args(argv)
  from experiments.cli import load_config
  from nlosjax.plan import dry_run, format_plan
  from nlosjax.train import RunConfig
  config = RunConfig.from_dict(load_config(args.config))
  report = format_plan(dry_run(config))
  command = "python -m benchmarks.dry_run" + (f" --config {args.config}" if args.config != "paper" else "")
  lines = [f"# Dry run of the `{args.config}` preset: memory and time before any data exist", ""]
  lines += _machine.provenance(command) + ["", report, "",
      "How to read it: `planned peak` is XLA's buffer plan for one step on one device"
      " (`compiled.memory_analysis()`: arguments + outputs + temporaries - donated buffers);"
      " the run itself (`train.check_memory`, set in the paper preset) refuses before making"
      " data when it exceeds 90 % of the device's memory. The time is an estimate: steps"
      " measured at reduced sizes, extrapolated linearly in FLOPs (`nlosjax.plan`);"
      " on a machine with other jobs (load average above) it is an upper bound.",
      "The paper trains on A100 GPUs (Sec. 5.1) and reports 17 GB for inference alone (Table 4);"
      " this file's machine is named above."]
  text = "\n".join(lines) + "\n"
  print(text)
  pathlib.Path(args.out).write_text(text)
  print(f"wrote {args.out}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
