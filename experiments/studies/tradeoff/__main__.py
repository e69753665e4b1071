"""``python -m experiments.studies.tradeoff``: the command line of the study (:mod:`experiments.studies.tradeoff`).

Parses the flags, runs :func:`~experiments.studies.tradeoff.study.run` and writes ``OUT/tradeoff.json``,
``OUT/tradeoff.png`` and ``OUT/tradeoff.md`` (printed too). The ``--help`` description is the
first line of the package docstring.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

from experiments.studies import tradeoff
from experiments.studies.tradeoff.configs import (
  APERTURE,
  DEFAULT_OUT_DIR,
  DEFAULT_WORKDIR,
  FULL_REPEATS,
  FULL_STEPS,
  KNOBS,
  QUICK_REPEATS,
  QUICK_STEPS,
)
from experiments.studies.tradeoff.figure import plot
from experiments.studies.tradeoff.machine import load_average, machine_line
from experiments.studies.tradeoff.report import to_markdown
from experiments.studies.tradeoff.study import run


def main(argv=None) -> dict:
  parser = argparse.ArgumentParser(prog="python -m experiments.studies.tradeoff",
                                   description=tradeoff.__doc__.split("\n\n")[0])
  parser.add_argument("--quick", action="store_true",
                      help=f"CI-sized: {QUICK_STEPS} training steps, {QUICK_REPEATS} timed calls")
  parser.add_argument("--steps", type=int, default=None,
                      help=f"training steps of every learned configuration (default {FULL_STEPS};"
                      f" --quick {QUICK_STEPS})")
  parser.add_argument("--repeats", type=int, default=None,
                      help=f"interleaved timing rounds (default {FULL_REPEATS}; --quick {QUICK_REPEATS})")
  parser.add_argument("--batch", type=int, default=8, help="frames per call (default 8)")
  parser.add_argument("--aperture", type=float, default=APERTURE,
                      help=f"Setup.aperture (m) of the R|a and R/2|a gating rows (default {APERTURE})")
  parser.add_argument("--knobs", default=",".join(KNOBS),
                      help=f"comma-separated subset of {','.join(KNOBS)} (method is always run)")
  parser.add_argument("--workdir", default=str(DEFAULT_WORKDIR),
                      help=f"checkpoints of the learned configurations (default {DEFAULT_WORKDIR})")
  parser.add_argument("--out-dir", default=str(DEFAULT_OUT_DIR),
                      help=f"where tradeoff.md, .json and .png go (default {DEFAULT_OUT_DIR})")
  args = parser.parse_args(argv)
  args.steps = args.steps or (QUICK_STEPS if args.quick else FULL_STEPS)
  args.repeats = args.repeats or (QUICK_REPEATS if args.quick else FULL_REPEATS)
  args.knobs = {"method"} | {k for k in args.knobs.split(",") if k}
  if not args.knobs <= set(KNOBS):
    parser.error(f"--knobs: unknown {sorted(args.knobs - set(KNOBS))}; choose from {KNOBS}")
  if args.steps < 1 or args.repeats < 1 or args.batch < 1:
    parser.error("--steps, --repeats and --batch must be >= 1")
  cmd = "python -m experiments.studies.tradeoff " + " ".join(argv if argv is not None else sys.argv[1:])
  before = load_average()
  res = run(args)
  after = load_average()
  machine = machine_line()
  res.update(command=cmd.strip(), machine=machine, load_before=before, load_after=after)
  out = pathlib.Path(args.out_dir)
  out.mkdir(parents=True, exist_ok=True)
  (out / "tradeoff.json").write_text(json.dumps(res, indent=1, default=float) + "\n")
  plot(res, out / "tradeoff.png")
  md = to_markdown(res, cmd.strip(), machine, (before, after))
  (out / "tradeoff.md").write_text(md)
  print(md)
  return res


if __name__ == "__main__":
  main()
