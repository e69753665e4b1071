"""Evaluate a trained run on test sequences made by an independent generator.

    python -m experiments.studies.independent_test [--checkpoint runs/default] [--sequences 8]
        [--frames 8] [--seed 2026] [--data PATH] [--first-seed-only]
        [--out experiments/studies/independent_test/results/table1_independent.md]

The test file comes from :mod:`experiments.independent_set` (stroke-font
letters and digits, bar and dot charts and other shapes; other motions, a
per-point renderer with exact distances, its own noise code; no code shared
with the training generator), written if absent; ``--data`` defaults to the
run config's ``independent.path``. The main job
scores its own models on the same set (``results/table1_independent.md`` in
its workdir); this script scores any run's checkpoints (every training seed's
``<variant>[-seed<k>]`` folder unless ``--first-seed-only``) and every classic
method (:func:`nlosjax.evaluation.protocol.evaluate`; classic settings as the
run chose them on its validation split) and writes the table with intervals
over sequences to ``--out`` (and ``.json``), with the command, date, machine
and commit.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

#: This study's results folder: its reports, figures and JSON records.
RESULTS = pathlib.Path(__file__).resolve().parent / "results"


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--checkpoint", default="runs/default")
  parser.add_argument("--sequences", type=int, default=8)
  parser.add_argument("--frames", type=int, default=8)
  parser.add_argument("--seed", type=int, default=2026)
  parser.add_argument("--data", default=None,
                      help="independent set (default: the run config's independent.path)")
  parser.add_argument("--out", default=str(RESULTS / "table1_independent.md"))
  parser.add_argument("--first-seed-only", action="store_true",
                      help="score only each variant's own folder, not its -seed<k> folders")
  args = parser.parse_args(argv)
  from experiments.provenance import provenance
  from nlosjax import inference
  from nlosjax import train as T
  from nlosjax.evaluation import protocol, report
  t0 = time.perf_counter()
  config, trained = inference.load_run(args.checkpoint, seeds=not args.first_seed_only)
  n_seeds = {v: (len(m) if isinstance(m, list) else 1) for v, m in trained.items()}
  from experiments.independent_set import GENERATOR_VERSION as generator
  from experiments.independent_set import ensure_independent_set
  path = args.data or (config.get("independent") or {}).get("path", "runs/data/independent-cpu.h5")
  data = ensure_independent_set(path, config["data"], args.sequences, args.frames, args.seed)
  chosen = pathlib.Path(args.checkpoint) / "results" / "validation.json"
  choices = json.loads(chosen.read_text()) if chosen.exists() else {}
  settings, best = choices.get("classic", {}), choices.get("best_classic")
  thresholds = {v: c["threshold"] for v, c in choices.get("learned", {}).items()}
  evaluation = protocol.evaluate(T.RunConfig.from_dict(config), data, trained, classic_settings=settings,
                                 model_thresholds=thresholds)
  table, comparisons = protocol.tabulate(evaluation, best_classic_method=best)
  cmd = "python -m experiments.studies.independent_test " + " ".join(sys.argv[1:] if argv is None else argv)
  where = (f"the settings the run chose on its validation split (`{chosen}`)" if settings
           else "their defaults (the run recorded no validation choices)")
  seeds = ", ".join(f"{v} {k}" for v, k in n_seeds.items())
  caption = (f"Models from `{args.checkpoint}` (the main job's CPU preset; each variant's "
             f"checkpoint chosen on validation; training seeds per variant: {seeds}, intervals "
             f"over sequences and seeds), evaluated on {args.sequences} sequences x "
             f"{args.frames} frames of `experiments.independent_set` (generator "
             f"`{generator}`: stroke-font letters and digits, bar and dot charts, rings, "
             "crosses, ellipses, triangles, L-shapes, some dim; bouncing linear motion with "
             "depth oscillation, no helix; a per-point renderer with exact distances and "
             "cosines; its own noise code), "
             "the run's Setup and detector ranges; classic methods on the interpolated "
             f"under-scanned input with {where}. Nothing is chosen on this file. "
             f"{time.perf_counter() - t0:.0f} s.")
  out = pathlib.Path(args.out)
  out.parent.mkdir(parents=True, exist_ok=True)
  text = ["# Table 1 on independently generated test sequences", ""] + provenance(cmd.strip()) + [""]
  body = report.format_tables(table, caption)
  if comparisons:
    body += "\n" + report.format_comparisons(comparisons)
  out.write_text("\n".join(text) + "\n" + body)
  out.with_suffix(".json").write_text(json.dumps({"table": table, "comparisons": comparisons},
                                                 indent=2) + "\n")
  from nlosjax.evaluation.figures import plot_comparison
  plot_comparison(evaluation["images"], out.with_name(out.stem + "_comparison.png"))
  print(out.read_text())
