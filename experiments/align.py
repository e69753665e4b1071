"""The second training stage on unlabelled measured scans, leave one scan out.

    python -m experiments.align --checkpoint runs/real [--variants ours ours_s] [--data-dir DIR]
        [--steps 100] [--lam 1.0] [--learning-rate 1e-4] [--workdir runs/align] [--data FILE]

For each measured scan (``--data-dir``, the scans of ``experiments.real_undersampling``)
and each variant of the trained run ``--checkpoint`` (a workdir of
``python -m experiments.train``, or ``pretrained:NAME`` for the weights shipped as
``NAME-<variant>``): the run's network trained on
:func:`nlosjax.train.align.align` with the run's synthetic data and the measured
inputs of every *other* scan (each under-scanned at all ``stride^2`` offsets of
the trained stride, time summed to the trained bins), into
``WORKDIR/<variant>-without-<scene>/`` (``params.npz``, ``align.json``). So a
scan's score (``python -m experiments.real_undersampling --aligned WORKDIR``)
comes from a network that never read that scan. Steps, ``lam`` and the
learning rate are fixed before any score is seen. A folder that holds
``params.npz`` is skipped (the command resumes). The synthetic data are the
run config's ``data.path`` unless ``--data`` names the file; an absent file is
generated from the run config's data spec first (``nlosjax.train.ensure_dataset``).
"""

from __future__ import annotations

import argparse
import pathlib
import sys

import numpy as np


def measured_inputs(files, model_config) -> dict:
  """``scene -> [stride^2, F, T, h, w]``: each scan at the model's bins, under-scanned at every offset."""
  from experiments.real_undersampling import scene_name
  from nlosjax import inference
  from nlosjax.data import io
  out = {}
  s = model_config.stride
  for path in files:
    x, setup = io.load_measurement(path)
    prepared = inference.adapt_to_capture(model_config, setup).prepare(x)          # [T, H, W]
    h, w = model_config.input_grid
    views = np.stack([prepared[:, a::s, b::s][:, :h, :w] for a in range(s) for b in range(s)])
    out[scene_name(pathlib.Path(path))] = np.repeat(views[:, None], model_config.frames, axis=1)
  return out


def fold_folder(workdir, variant: str, scene: str) -> pathlib.Path:
  return pathlib.Path(workdir) / f"{variant}-without-{scene}"


def load_source(checkpoint: str, variants) -> tuple[dict, dict]:
  """``(run config, variant -> (model_config, params))`` of a workdir or ``pretrained:NAME``."""
  from nlosjax import inference
  if checkpoint.startswith("pretrained:"):
    name, trained, config = checkpoint[len("pretrained:"):], {}, None
    for variant in variants:
      try:
        mcfg, params, provenance = inference.load_pretrained(name, variant)
      except ValueError as e:
        raise SystemExit(f"{checkpoint}: {e}") from None
      trained[variant], config = (mcfg, params), provenance["config"]
    return config, trained
  config, trained = inference.load_run(checkpoint)
  missing = [v for v in variants if v not in trained]
  if missing:
    raise SystemExit(f"{checkpoint}: no trained {' '.join(missing)} (it has {sorted(trained)})")
  return config, trained


def main(argv=None) -> int:
  from experiments.real_undersampling import default_files
  from nlosjax import train as T
  from nlosjax.evaluation import protocol
  from nlosjax.train.align import align
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--checkpoint", required=True,
                      help="a run of python -m experiments.train (its workdir), or pretrained:NAME")
  parser.add_argument("--variants", nargs="+", default=["ours", "ours_s"])
  parser.add_argument("--data-dir", default=None, help="folder of measured .mat scans")
  parser.add_argument("--steps", type=int, default=100)
  parser.add_argument("--lam", type=float, default=1.0)
  parser.add_argument("--learning-rate", type=float, default=1e-4)
  parser.add_argument("--workdir", default="runs/align")
  parser.add_argument("--data", default=None,
                      help="the synthetic dataset file (default: the run config's data.path)")
  args = parser.parse_args(argv)
  files = default_files(args.data_dir)
  if len(files) < 2:
    raise SystemExit("leave-one-scan-out needs at least two measured scans")
  config, trained = load_source(args.checkpoint, args.variants)
  config = T.with_defaults(config)
  data_path = pathlib.Path(args.data or config["data"]["path"])
  T.ensure_dataset(config, data_path)
  validate = protocol.validation_psnr(config, data_path)
  for variant in args.variants:
    mcfg, params = trained[variant]                # load_run without seeds: (model_config, params)
    inputs = measured_inputs(files, mcfg)
    for scene in inputs:
      folder = fold_folder(args.workdir, variant, scene)
      if (folder / "params.npz").exists():
        print(f"[align] {folder}: done already")
        continue
      others = np.concatenate([v for k, v in inputs.items() if k != scene])
      print(f"[align] {variant} without {scene}: {len(others)} measured inputs")
      align(config, data_path, mcfg, params, others, folder, steps=args.steps, lam=args.lam,
            learning_rate=args.learning_rate, validate=validate)
  return 0


if __name__ == "__main__":
  sys.exit(main())
