"""Table 1 at the CPU preset over several training seeds: ``experiments/studies/table1/results/table1.md``.

    python -m experiments.studies.table1 [--seeds 3] [--config cpu] [--workdir runs/table1]
                                [--out experiments/studies/table1/results/table1.md] [overrides ...]

Runs the main job (:func:`experiments.main_job.train_and_evaluate`, the code
behind ``python -m experiments.train``) with ``--seeds`` training seeds per
learned variant, so every interval covers the training run as well as the
test sequences, then writes the results file whole: provenance (command,
date, machine, commit), the main job's ``table.md`` (Table 1 with intervals,
the object-aware table, the temporal-consistency table, the paired
differences with their verdicts, the choices made on the validation split),
and beside it ``table1.json`` (the table, the comparisons and the validation
choices) and the figures.
Resumable: a rerun reuses the workdir's finished models. Superseded by the plateau-trained
mechanism study (``experiments/studies/archive/README.md``); kept to rerun the paper's table
at a fixed step count. The main job's own time is ``benchmarks/results/main_job.md``'s.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import shutil
import sys
import time

#: This study's results folder: its reports, figures and JSON records.
RESULTS = pathlib.Path(__file__).resolve().parent / "results"


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--config", default="cpu")
  parser.add_argument("--seeds", type=int, default=3)
  parser.add_argument("--workdir", default="runs/table1")
  parser.add_argument("--out", default=str(RESULTS / "table1.md"))
  args, overrides = parser.parse_known_args(argv)
  if args.seeds < 1:
    parser.error(f"--seeds must be >= 1, got {args.seeds}")
  from experiments.cli import load_config
  from experiments.main_job import train_and_evaluate
  from experiments.provenance import provenance
  from nlosjax.train import RunConfig
  config = load_config(args.config, overrides)
  config.setdefault("train", {})["seeds"] = args.seeds
  t0 = time.perf_counter()
  cmd = "python -m experiments.studies.table1 " + " ".join(sys.argv[1:] if argv is None else argv)
  facts = provenance(cmd.strip())          # the commit the run starts from
  workdir = pathlib.Path(args.workdir)
  train_and_evaluate(RunConfig.from_dict(config), workdir)
  results = workdir / "results"
  out = pathlib.Path(args.out)
  out.parent.mkdir(parents=True, exist_ok=True)
  head = [f"# Table 1 at the `{args.config}` preset, {args.seeds} training seed(s)", ""]
  head += facts
  head += [f"- Wall time of this command: {(time.perf_counter() - t0) / 60:.1f} min "
           "(a rerun reuses finished models)", ""]
  out.write_text("\n".join(head) + "\n" + (results / "table.md").read_text())
  bundle = {name: json.loads((results / f"{name}.json").read_text())
            for name in ("table", "comparisons", "validation")}
  out.with_suffix(".json").write_text(json.dumps(bundle, indent=2) + "\n")
  for name in ("comparison", "training_curves"):
    src = results / f"{name}.png"
    if src.exists():
      shutil.copyfile(src, out.with_name(f"{out.stem}_{name}.png"))
  print(out.read_text())
