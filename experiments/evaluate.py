"""Evaluate trained models and the classic methods on a dataset file: Table 1 for any HDF5 file.

Usage::

  python -m experiments.evaluate --checkpoint runs/default --data runs/data/cpu-v3.h5
  python -m experiments.evaluate --checkpoint runs/default/ours --data other.h5 --out runs/eval

``--checkpoint`` is a main-job workdir (every trained variant in it is
evaluated), one variant's folder (``WORKDIR/ours``) or its ``checkpoints``
folder. ``--data`` is any file in the documented dataset layout
(``docs/dataset.md``), not only ones our generator made; the models are
moved to the file's Setup (same parameters, physics layer rebuilt) and the
classic methods get the under-scanned input interpolated to the full grid,
as in the paper, with the settings the run chose on its validation split
(``WORKDIR/results/validation.json``; defaults when the run has none, or
``--retune`` to choose them on this file's ``val`` split); the learned
models' surface thresholds come from the same place. Prints the table
and writes ``OUT/table.md``, ``OUT/table.json`` (method -> metric ->
``{"mean", "ci95", "std", "n_sequences", "n_frames", "n_seeds"}``; intervals
over sequences), ``OUT/comparisons.json`` and ``OUT/comparison.png``.
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time


def main(argv=None) -> dict:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--checkpoint", required=True,
                      help="training workdir, variant folder, or its checkpoints folder")
  parser.add_argument("--data", required=True, help="HDF5 dataset file in the documented layout")
  parser.add_argument("--split", default="test", help="split of the file to evaluate (default test)")
  parser.add_argument("--out", default=None,
                      help="output folder (default: <workdir>/eval_<data file stem>)")
  parser.add_argument("--classic", default="fbp,lct,fk,phasor,rsd",
                      help="comma-separated classic methods to include ('' for none)")
  parser.add_argument("--retune", action="store_true",
                      help="choose the classic settings on this file's val split")
  from experiments import xla_cache
  xla_cache.add_argument(parser)
  args = parser.parse_args(argv)
  xla_cache.enable_unless(args.no_cache)     # before anything compiles
  from experiments.cli import one_line_errors
  with one_line_errors():           # a bad or damaged input, a full disk: one line, exit status 2
    return _run(args)


def _run(args) -> dict:
  import json

  from nlosjax import inference, train
  from nlosjax.data.dataset import open_dataset
  from nlosjax.evaluation import baselines, protocol
  t0 = time.perf_counter()
  data = pathlib.Path(args.data)
  if not data.is_file():
    raise SystemExit(f"--data {data}: no such file")
  classic = tuple(m for m in args.classic.split(",") if m)
  unknown = set(classic) - set(baselines.CLASSIC_METHODS)
  if unknown:
    raise SystemExit(f"--classic: unknown method(s) {sorted(unknown)}; known {baselines.CLASSIC_METHODS}")
  try:
    with open_dataset(data) as ds:
      setup = ds.setup
      if not ds.names(args.split):
        raise ValueError(f"{data}: no sequence in split {args.split!r}")
    config, trained = inference.load_run(args.checkpoint, setup=setup)
    config = train.RunConfig.from_dict(config)
    workdir, _, _ = inference.find_checkpoints(args.checkpoint)
    chosen = workdir / "results" / "validation.json"
    settings, best, source = {}, None, "defaults (the run chose none)"
    thresholds = {}
    if args.retune:
      batch = config.train.eval_batch
      val = protocol.load_split(config, data, "val", batch_size=batch)
      val["loader"].close()
      settings = baselines.tune(val["measurement"], val["intensity"], val["depth"], val["setup"],
                                val["stride"], methods=classic, batch_size=batch)
      thresholds = {v: c["threshold"] for v, c in
                    protocol.tune_model_thresholds(config, data, trained).items()}
      source = f"chosen on the val split of `{data}`"
    elif chosen.exists():
      try:
        run_choices = json.loads(chosen.read_text())
      except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{chosen}: not readable JSON ({e}); rerun the main job on {workdir} to "
                         "write it again, or pass --retune") from None
      settings, best = run_choices.get("classic", {}), run_choices.get("best_classic")
      thresholds = {v: c["threshold"] for v, c in run_choices.get("learned", {}).items()}
      source = f"chosen on the run's validation split (`{chosen}`)"
    if settings and best is None:
      best = max(settings, key=lambda m: settings[m]["psnr"])
    evaluation = protocol.evaluate(config, data, trained, split=args.split, methods=classic,
                                   classic_settings=settings, model_thresholds=thresholds)
    table, comparisons = protocol.tabulate(
        evaluation, best_classic_method=best if best in classic else None)
  except ValueError as e:
    from nlosjax.files import one_line
    raise SystemExit(f"error: {one_line(str(e))}") from None   # bad arguments: exit status 1
  out = pathlib.Path(args.out) if args.out else workdir / f"eval_{data.stem}"
  caption = (f"`{args.split}` split of `{data}` ({evaluation['n_frames']} frames); "
             f"models from `{args.checkpoint}`; classic settings {source}; "
             f"evaluated in {time.perf_counter() - t0:.0f} s.")
  protocol.write_results(out, table, comparisons, evaluation["images"], caption=caption)
  print((out / "table.md").read_text())
  print(f"results written to {out}")
  return table


if __name__ == "__main__":
  sys.exit(main() is None)
