"""The second training stage on unlabelled measured scans, leave one scan out.

    python -m experiments.studies.align --checkpoint runs/real [--variants ours ours_s] [--data-dir DIR]
        [--steps 100] [--lam 1.0 | --lam balanced] [--layer st_mamba0 | --layer auto]
        [--learning-rate 1e-4] [--workdir runs/align] [--data FILE]

For each measured scan (``--data-dir``, the scans of ``experiments.studies.real_undersampling``)
and each variant of the trained run ``--checkpoint`` (a workdir of
``python -m experiments.train``, or ``pretrained:NAME`` for the weights shipped as
``NAME-<variant>``): the run's network trained on
:func:`experiments.studies.alignment.align` with the run's synthetic data and the measured
inputs of every *other* scan (each under-scanned at all ``stride^2`` offsets of
the trained stride, time summed to the trained bins), into
``WORKDIR/<variant>-without-<scene>/`` (``params.npz``, ``align.json``). So a
scan's score (``python -m experiments.studies.real_undersampling --aligned WORKDIR``)
comes from a network that never read that scan. Steps, ``lam`` and the
learning rate are fixed before any score is seen. A finished fold (its folder
holds ``params.npz`` and ``align.json``) is skipped, so the command resumes. The synthetic data are the
run config's ``data.path`` unless ``--data`` names the file; an absent file is
generated from the run config's data spec first (``nlosjax.train.ensure_dataset``).

``--lam balanced`` sets each fold's ``lam`` from the training side alone: the MMD term's
gradient as large as the synthetic loss's, in the median over 8 synthetic training
batches, at the starting parameters, with that fold's measured inputs
(:func:`experiments.studies.alignment.balanced_lam`); the norms and the ``lam`` are recorded in the
fold's ``align.json`` (``"lam_rule"``).

``--layer auto`` chooses each fold's aligned layer from the training side too: among the
network's layers that keep a feature vector per time step and scan point (extraction,
ST-Mamba and cross blocks), the one whose features of the fold's measured inputs stand the
most noise widths away from those of 8 synthetic training batches
(:func:`experiments.studies.alignment.layer_separation`); the separations and the choice are recorded
(``"layer_rule"``), and a balanced ``lam`` is measured at that layer.
"""

from __future__ import annotations

import argparse
import pathlib
import sys
from typing import Callable

import numpy as np

from experiments.studies.real_undersampling.protocol import default_files, fold_files, fold_folder, scene_name
from nlosjax.variants import FAMILY_STMAMBA, VARIANTS

#: The variants aligned by default: the ST-Mamba networks (the stage fits their features).
STMAMBA = [name for name, v in VARIANTS.items() if v.family == FAMILY_STMAMBA]


def measured_inputs(files, model_config) -> dict:
  """``scene -> [stride^2, F, T, h, w]``: each scan at the model's bins, under-scanned at every offset."""
  from nlosjax import inference
  from nlosjax.data import io
  out = {}
  s = model_config.stride
  for path in files:
    x, setup = io.load_measurement(path)
    prepared = inference.for_capture(model_config, setup).prepare(x)          # [T, H, W]
    h, w = model_config.input_grid
    views = np.stack([prepared[:, a::s, b::s][:, :h, :w] for a in range(s) for b in range(s)])
    out[scene_name(pathlib.Path(path))] = np.repeat(views[:, None], model_config.frames, axis=1)
  return out


#: ``--lam balanced``: the MMD gradient this many times the synthetic one, over this many batches.
BALANCED_SHARE, BALANCED_BATCHES = 1.0, 8


def lam_arg(text: str) -> float | str:
  """``--lam``: a float >= 0, or ``balanced``."""
  if text == "balanced":
    return text
  try:
    value = float(text)
  except ValueError:
    raise argparse.ArgumentTypeError(f"--lam takes a number >= 0 or 'balanced', got {text!r}") from None
  if not value >= 0:
    raise argparse.ArgumentTypeError(f"--lam must be >= 0, got {text!r}")
  return value


def fold_lam(lam: float | str, config, data_path, model_config, params, measured,
             log: Callable[[str], None] = print, layer: str = "st_mamba0") -> tuple[float, dict | None]:
  """``(lam, rule record)``: ``lam`` itself, or for ``"balanced"`` the one measured on ``measured``
  (the MMD term at ``layer``)."""
  if lam != "balanced":
    return float(lam), None
  from experiments.studies.alignment import balanced_lam, term_gradient_norms
  norms = term_gradient_norms(config, data_path, model_config, params, measured, batches=BALANCED_BATCHES,
                              layer=layer)
  value = balanced_lam(norms, BALANCED_SHARE)
  log(f"[align] balanced lam {value:.4g} (median gradient norms: synthetic "
      f"{np.median(norms['synthetic']):.4g}, mmd {np.median(norms['mmd']):.4g})")
  return value, {"rule": "balanced", "share": BALANCED_SHARE, "batches": BALANCED_BATCHES, "norms": norms}


#: ``--layer auto``: the synthetic training inputs the layer is chosen against (batches of the
#: training split), and the separation's estimates (:func:`experiments.studies.alignment.layer_separation`).
AUTO_LAYER_BATCHES, AUTO_LAYER_DRAWS = 8, 16


def fold_layer(layer: str, config, data_path, model_config, params, measured,
               log: Callable[[str], None] = print) -> tuple[str, dict | None]:
  """``(layer, rule record)``: ``layer`` itself, or for ``"auto"`` the one whose features of
  ``measured`` (the fold's training scans) stand furthest from the synthetic training inputs'."""
  if layer != "auto":
    return layer, None
  from experiments.studies.alignment import chosen_layer, layer_separation
  from nlosjax.train import make_loader, select_frames
  loader = make_loader(config, data_path, "train", batch_size=config.train.batch_size,
                       shuffle=True, seed=0)
  try:
    synthetic = np.concatenate([select_frames(loader.batch(k)["measurement"], model_config.frames)
                                for k in range(AUTO_LAYER_BATCHES)])
  finally:
    loader.close()
  separation = layer_separation(model_config, params, synthetic, measured, draws=AUTO_LAYER_DRAWS)
  value = chosen_layer(separation)
  log("[align] layer separation (z, noise widths): "
      + ", ".join(f"{k} {v['z']:.1f}" for k, v in separation.items()) + f"; aligning {value}")
  return value, {"rule": "auto", "batches": AUTO_LAYER_BATCHES, "draws": AUTO_LAYER_DRAWS,
                 "separation": separation}


def align_folds(config, data_path, model_config, params, inputs: dict, workdir, variant: str, *,
                steps: int = 100, lam: float | str = 1.0, learning_rate: float = 1e-4, validate=None,
                layer: str = "st_mamba0",
                before_fold: Callable[[str], bool] | None = None,
                after_fold: Callable[[pathlib.Path], None] | None = None,
                log: Callable[[str], None] = print) -> tuple[bool, bool]:
  """Leave one scan out: for each scan of ``inputs``, ``params`` aligned on the *other* scans' inputs.

  ``inputs``: ``scene -> [n, F, T, h, w]`` (:func:`measured_inputs`); each fold trains
  :func:`experiments.studies.alignment.align` into :func:`fold_folder` ``(workdir, variant, scene)``;
  finished folds (:func:`fold_files`) are skipped. ``lam``: a number, or ``"balanced"``
  (:func:`fold_lam`, measured per fold). ``layer``: the aligned layer, or ``"auto"``
  (:func:`fold_layer`, chosen per fold on the fold's training scans). ``before_fold(scene)`` returning False
  stops before that fold (a deadline); ``after_fold(folder)`` runs after each one trained.
  Returns ``(every fold finished, at least one trained now)``.
  """
  from experiments.studies.alignment import align
  started = False
  for scene in inputs:
    folder = fold_folder(workdir, variant, scene)
    if fold_files(folder):
      log(f"[align] {folder}: done already")
      continue
    if before_fold is not None and not before_fold(scene):
      return False, started
    others = np.concatenate([v for k, v in inputs.items() if k != scene])
    log(f"[align] {variant} without {scene}: {len(others)} measured inputs")
    chosen, layer_rule = fold_layer(layer, config, data_path, model_config, params, others, log)
    value, rule = fold_lam(lam, config, data_path, model_config, params, others, log, layer=chosen)
    extra = {**({} if rule is None else {"lam_rule": rule}),
             **({} if layer_rule is None else {"layer_rule": layer_rule})}
    align(config, data_path, model_config, params, others, folder, steps=steps, lam=value,
          learning_rate=learning_rate, validate=validate, log=log, layer=chosen, extra=extra or None)
    started = True
    if after_fold is not None:
      after_fold(folder)
  return True, started


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
  from nlosjax import train as T
  from nlosjax.evaluation import protocol
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--checkpoint", required=True,
                      help="a run of python -m experiments.train (its workdir), or pretrained:NAME")
  parser.add_argument("--variants", nargs="+", default=STMAMBA,
                      help=f"the variants to align (default: the ST-Mamba ones, {' '.join(STMAMBA)})")
  parser.add_argument("--data-dir", default=None, help="folder of measured .mat scans")
  parser.add_argument("--steps", type=int, default=100)
  parser.add_argument("--lam", type=lam_arg, default=1.0,
                      help="the MMD term's weight, or 'balanced' (measured per fold; module docstring)")
  parser.add_argument("--learning-rate", type=float, default=1e-4)
  parser.add_argument("--layer", default="st_mamba0",
                      help="the aligned layer (a sub-module of the network), or 'auto': per fold the layer "
                           "whose features of the fold's training scans stand furthest from the synthetic ones")
  parser.add_argument("--workdir", default="runs/align")
  parser.add_argument("--data", default=None,
                      help="the synthetic dataset file (default: the run config's data.path)")
  args = parser.parse_args(argv)
  files = default_files(args.data_dir)
  if len(files) < 2:
    raise SystemExit("leave-one-scan-out needs at least two measured scans")
  config, trained = load_source(args.checkpoint, args.variants)
  config = T.RunConfig.from_dict(config)
  data_path = pathlib.Path(args.data or config.data.path)
  T.ensure_dataset(config, data_path)
  validate = protocol.validation_psnr(config, data_path)
  for variant in args.variants:
    mcfg, params = trained[variant]                # load_run without seeds: (model_config, params)
    align_folds(config, data_path, mcfg, params, measured_inputs(files, mcfg), args.workdir, variant,
                steps=args.steps, lam=args.lam, learning_rate=args.learning_rate, validate=validate,
                layer=args.layer)
  return 0


if __name__ == "__main__":
  sys.exit(main())
