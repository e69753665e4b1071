"""The evaluation protocol: every method on one split of a dataset file, scored per frame.

:func:`evaluate` reads a split with the config's loader (frames in file
order: sequence, then middle frame), reconstructs the middle frame of each
triplet with every classic method (under-scanned input interpolated to the
full grid, settings from :func:`nlosjax.evaluation.baselines.tune`) and every
trained model (each of its seeds), and scores each frame, and each pair of
consecutive middle frames of a sequence for the temporal scores, seed by seed
(:func:`nlosjax.evaluation.scores.frame_scores`). :func:`tabulate` turns that
into the table (mean and 95 % interval over sequences and seeds) and the
paired comparisons a claim rests on; :func:`write_results` writes them.

Which split is read is the caller's choice: ``"val"`` for every choice
(classic settings, checkpoints, the best classic method), ``"test"`` only for
final tables.
"""

from __future__ import annotations

import functools
import json
import pathlib
from typing import Callable

import jax.numpy as jnp
import numpy as np

from nlosjax.evaluation import baselines, figures, report, scores
from nlosjax.train.config import RunConfig
from nlosjax.variants import COMPARISONS, VARIANTS

__all__ = ["load_split", "model_images", "validation_scores", "validation_psnr", "surface_cut",
           "choose_surface_threshold", "tune_model_thresholds",
           "evaluate", "tabulate", "best_classic", "write_results"]

#: Surface thresholds tried for a learned model on validation: 0 keeps the model's own depth
#: map (its soft projection already sets pixels below its ``depth_threshold`` to background),
#: the rest are the classic methods' candidates.
MODEL_THRESHOLDS = (0.0,) + tuple(baselines.THRESHOLDS)


def load_split(config: RunConfig, data_path, split: str, *, batch_size: int) -> dict:
  """Ground truth and middle-frame input of every example of ``split``.

  Returns:
    ``{"intensity" [N, H, W], "depth" [N, H, W], "measurement" [N, T, h, w]
    (the middle frame), "sequence" [N] int, "frame" [N] int (the middle
    frame's index in its sequence), "setup", "stride", "loader"}``;
    the open ``loader`` (unshuffled) feeds :func:`model_images`; close it.
  """
  from nlosjax.train import make_loader
  loader = make_loader(config, data_path, split, batch_size=batch_size,
                       shuffle=False, seed=0)
  gi, gd, mid, seq, frame = [], [], [], [], []
  for step in range(len(loader)):
    b = loader.batch(step)
    gi.append(b["intensity"])
    gd.append(b["depth"])
    mid.append(b["measurement"][:, b["measurement"].shape[1] // 2])
    seq.append(b["sequence"])
    frame.append(b["frame"])
  return {"intensity": np.concatenate(gi), "depth": np.concatenate(gd),
          "measurement": np.concatenate(mid), "sequence": np.concatenate(seq),
          "frame": np.concatenate(frame), "setup": loader.setup, "stride": loader.stride, "loader": loader}


@functools.lru_cache(maxsize=8)
def _jitted_apply(mcfg):
  """The model's jitted forward, one per model config (checkpoints and seeds share it).

  Compiled with nlosjax's input checks (:func:`nlosjax.physics.checks.checked`): a
  NaN, infinite or negative count in a batch raises ``ValueError`` instead of
  scoring a plausible image.
  """
  from nlosjax.physics.checks import checked
  model = mcfg.module()
  return checked(lambda p, x: model.apply({"params": p}, x), operators=mcfg.physics_operators())


def model_images(mcfg, params, loader) -> dict:
  """Intensity and depth of a trained model on a loader's examples (in order).

  The intensity is clamped to [0, 1], the range of the ground truth and of
  every metric (Ours' is already in it; USM's head is not clamped, and USM's
  own evaluation clamps it the same way).

  Returns ``{"intensity": [N, H, W], "depth": [N, H, W]}`` NumPy.
  """
  from nlosjax.train import select_frames
  apply = _jitted_apply(mcfg)
  inten, depth = [], []
  for step in range(len(loader)):
    x = select_frames(loader.batch(step)["measurement"], mcfg.frames)
    out = apply(params, jnp.asarray(x))
    inten.append(np.clip(np.asarray(out["intensity"]), 0.0, 1.0))
    depth.append(np.asarray(out["depth"]))
  return {"intensity": np.concatenate(inten), "depth": np.concatenate(depth)}


def validation_scores(config: RunConfig, data_path, *, split: str = "val") -> Callable:
  """``(model_config, params) -> {score: mean over the frames of split}``: the checkpoint criteria.

  The scores (dB where PSNR; higher is better but for the error): ``psnr`` (whole-image
  intensity PSNR), ``psnr_balanced`` (object and background pixels weighted equally,
  :func:`nlosjax.metrics.psnr_balanced`), ``intensity_mae_object`` and ``f1`` (of the
  model's own depth map: surface where it is at least
  :data:`nlosjax.metrics.SURFACE_MIN_DEPTH`). ``train.stop.metric`` names the one a
  run stops and chooses on (:class:`nlosjax.train.StopRule`); the others ride along in
  its validation curve. Frames without objects are left out of the object scores' means.
  """
  from nlosjax import metrics
  batch_size = config.train.eval_batch

  def score(mcfg, params) -> dict:
    data = load_split(config, data_path, split, batch_size=batch_size)
    try:
      im = model_images(mcfg, params, data["loader"])
    finally:
      data["loader"].close()
    gi, gd = data["intensity"], data["depth"]
    out = {"psnr_balanced": metrics.psnr_balanced(im["intensity"], gi, gd),
           "intensity_mae_object": metrics.intensity_mae_object(im["intensity"], gi, gd),
           "f1": metrics.f1(im["depth"], gd)}
    return {"psnr": float(np.mean(np.asarray(metrics.psnr(im["intensity"], gi)))),
            **{k: float(np.nanmean(np.asarray(v, np.float64))) for k, v in out.items()}}

  return score


def validation_psnr(config: RunConfig, data_path, *, split: str = "val") -> Callable:
  """``(model_config, params) -> mean intensity PSNR (dB)`` on ``split``: the whole-image criterion."""
  scores = validation_scores(config, data_path, split=split)
  return lambda mcfg, params: scores(mcfg, params)["psnr"]


def surface_cut(intensity, depth, threshold: float) -> np.ndarray:
  """``depth`` with every pixel whose ``intensity`` is below ``threshold`` set to background (0 m).

  The rule :func:`nlosjax.physics.intensity_depth` applies to the classic
  methods (intensity normalised to a peak of 1), applied to a learned
  model's output. ``intensity``, ``depth``: ``[..., H, W]``; threshold 0
  returns ``depth`` unchanged.
  """
  depth = np.asarray(depth)
  if threshold <= 0:
    return depth
  return np.where(np.asarray(intensity) >= threshold, depth, 0.0).astype(depth.dtype)


def _as_seeds(models) -> list:
  return [models] if isinstance(models, tuple) else list(models)


def tune_model_thresholds(config: RunConfig, data_path, trained: dict, *, split: str = "val",
                          thresholds=MODEL_THRESHOLDS, log: Callable[[str], None] = print) -> dict:
  """Each learned variant's surface threshold, chosen on ``split`` as for the classic methods.

  The threshold (:func:`surface_cut` of the model's intensity and depth) with
  the highest mean surface F1 over the split's frames and the variant's
  seeds wins; ties keep the earlier candidate (0 first: the model as it is).

  Args:
    config, data_path, trained: as :func:`evaluate`.
    thresholds: candidates (fractions of the peak intensity).
  Returns:
    ``variant -> {"threshold": float, "f1": float, "f1_by_threshold": {str(th): float}}``.
  """
  batch_size = config.train.eval_batch
  data = load_split(config, data_path, split, batch_size=batch_size)
  out = {}
  try:
    for variant, models in trained.items():
      ims = [model_images(mcfg, params, data["loader"]) for mcfg, params in _as_seeds(models)]
      out[variant] = choose_surface_threshold(ims, data["depth"], thresholds)
      log(f"[tune] {variant}: surface threshold {out[variant]['threshold']} "
          f"(validation surface F1 {out[variant]['f1']:.3f})")
  finally:
    data["loader"].close()
  return out


def choose_surface_threshold(images: list[dict], gt_depth, thresholds=MODEL_THRESHOLDS) -> dict:
  """The threshold with the best mean surface F1 over frames and seeds (ties: the earlier one).

  Args:
    images: one ``{"intensity", "depth"}`` (``[N, H, W]`` each) per seed.
    gt_depth: ``[N, H, W]`` true depth, metres (0 = background).
    thresholds: candidates for :func:`surface_cut`.
  Returns:
    ``{"threshold": float, "f1": float, "f1_by_threshold": {str(th): float}}``.
  """
  from nlosjax import metrics
  f1 = {}
  for th in thresholds:
    f1[str(float(th))] = float(np.nanmean([
        np.asarray(metrics.surface_scores(surface_cut(im["intensity"], im["depth"], th),
                                          gt_depth)["f1"]) for im in images]))
  best = max(f1, key=lambda t: (f1[t], -list(f1).index(t)))
  return {"threshold": float(best), "f1": f1[best], "f1_by_threshold": f1}


def evaluate(config: RunConfig, data_path, trained: dict, *, split: str = "test",
             methods: tuple[str, ...] = baselines.CLASSIC_METHODS,
             classic_settings: dict | None = None, model_thresholds: dict | None = None,
             log: Callable[[str], None] = print) -> dict:
  """Every method on ``split`` of ``data_path``, scored per frame.

  Args:
    config: the run config (its ``data`` and ``train.eval_batch_size``).
    data_path: an HDF5 file in the documented layout.
    trained: ``variant -> (model_config, params)`` or ``variant -> [(model_config,
      params), ...]`` (one per training seed).
    split: the split to read.
    methods: the classic methods to include.
    classic_settings: ``method -> {"options", "threshold"}`` (from
      :func:`~nlosjax.evaluation.baselines.tune`); a method without an entry
      runs with its defaults.
    model_thresholds: ``variant -> surface threshold`` (from
      :func:`tune_model_thresholds`), applied to that variant's depth maps by
      :func:`surface_cut`; a variant without one is scored as the model outputs.
  Returns:
    ``{"scores": method -> metric -> [N] (classic) or [K, N] (K seeds),
    "sequence": [N], "frame": [N], "images": method -> {"intensity", "depth"}
    (first seed; plus "gt"), "split", "data", "n_frames"}``; the metrics are
    :data:`~nlosjax.evaluation.scores.TABLE_METRICS` (the temporal ones NaN at
    each sequence's first evaluated frame).
  """
  from tqdm import tqdm
  batch_size = config.train.eval_batch
  classic_settings = classic_settings or {}
  model_thresholds = model_thresholds or {}
  data = load_split(config, data_path, split, batch_size=batch_size)
  gt = {"intensity": data["intensity"], "depth": data["depth"]}
  # The temporal scores pair consecutive middle frames of one sequence, one method and seed at a time.
  where = {"sequence": data["sequence"], "frame": data["frame"]}
  images, per_frame = {"gt": gt}, {}
  try:
    for method in tqdm(methods, desc="classic methods", unit="method", disable=not methods):
      setting = classic_settings.get(method, {})
      out_i, out_d = [], []
      for s in range(0, len(data["measurement"]), batch_size):
        i, d = baselines.classic_images(data["measurement"][s:s + batch_size], data["setup"],
                                        data["stride"], method, setting.get("options"),
                                        setting.get("threshold", baselines.DEFAULT_THRESHOLD))
        out_i.append(i)
        out_d.append(d)
      images[method] = {"intensity": np.concatenate(out_i), "depth": np.concatenate(out_d)}
      per_frame[method] = scores.frame_scores(images[method]["intensity"], images[method]["depth"],
                                              gt["intensity"], gt["depth"], **where)
    for variant, models in trained.items():
      seeds = []
      for mcfg, params in _as_seeds(models):
        im = model_images(mcfg, params, data["loader"])
        im["depth"] = surface_cut(im["intensity"], im["depth"], model_thresholds.get(variant, 0.0))
        images.setdefault(variant, im)
        seeds.append(scores.frame_scores(im["intensity"], im["depth"], gt["intensity"],
                                         gt["depth"], **where))
      per_frame[variant] = {k: np.stack([s[k] for s in seeds]) for k in scores.TABLE_METRICS}
  finally:
    data["loader"].close()
  return {"scores": per_frame, "sequence": data["sequence"], "frame": data["frame"],
          "images": images, "split": split, "data": str(data_path),
          "n_frames": int(len(data["sequence"]))}


def best_classic(evaluation: dict, metric: str = "psnr") -> str | None:
  """The classic method with the best mean ``metric`` in an evaluation (use a validation one)."""
  sign = 1.0 if scores.HIGHER_IS_BETTER[metric] else -1.0
  found = {m: sign * float(np.nanmean(s[metric])) for m, s in evaluation["scores"].items()
           if m in baselines.CLASSIC_METHODS}
  return max(found, key=found.get) if found else None


def tabulate(evaluation: dict, *, best_classic_method: str | None = None, n_boot: int | None = None
             ) -> tuple[dict, list[dict]]:
  """The table and the paired comparisons of an :func:`evaluate` result.

  Comparisons, where both sides were evaluated: Ours - Ours-S, Ours - USM,
  Ours-S - USM, and each learned model - ``best_classic_method`` (chosen on
  validation by the caller), on every metric both sides hold (the temporal
  ones included: Ours - Ours-S on ``temporal_rmse`` asks whether the
  temporal input steadies the video).

  Returns:
    ``(table, comparisons)``: ``method -> metric -> {"mean", "ci95", "std",
    "n_sequences", "n_frames", "n_seeds"}``, and a list of ``{"a", "b",
    "label", "diff": metric -> the same keys for a - b}``.
  """
  kw = {} if n_boot is None else {"n_boot": n_boot}
  per_frame, seq = evaluation["scores"], evaluation["sequence"]
  table = {m: scores.summarize_scores(s, seq, **kw) for m, s in per_frame.items()}
  pairs = list(COMPARISONS)
  if best_classic_method is not None:
    pairs += [(v, best_classic_method) for v in VARIANTS]
  comparisons = [{"a": a, "b": b, "label": f"{report.label(a)} - {report.label(b)}",
                  "diff": scores.compare_scores(per_frame[a], per_frame[b], seq, **kw)}
                 for a, b in pairs if a in per_frame and b in per_frame]
  return table, comparisons


def write_results(out_dir, table: dict, comparisons: list[dict], images: dict, *, caption: str,
                  validation: dict | None = None, logs: dict | None = None,
                  stem: str = "table", evaluation: dict | None = None) -> None:
  """``table.json``, ``comparisons.json``, ``validation.json``, ``table.md``, figures in ``out_dir``.

  ``table.json`` is ``method -> metric -> {"mean", "ci95": [lo, hi], "std",
  "n_sequences", "n_frames", "n_seeds"}``. Another ``stem`` (a second test
  set) writes ``{stem}.json``, ``{stem}.md``, ``{stem}_comparisons.json`` and
  ``{stem}_comparison.png`` instead. With ``evaluation`` (an :func:`evaluate` result), its
  per-frame scores too, ``scores.npz`` (``{stem}_scores.npz``): ``<method>/<metric>``
  ``[N]`` or ``[seeds, N]`` and ``sequence``, ``frame`` ``[N]``, so any later comparison
  (each learned model against each classic method, on any score) pairs the same frames.
  """
  out = pathlib.Path(out_dir)
  out.mkdir(parents=True, exist_ok=True)
  prefix = "" if stem == "table" else f"{stem}_"
  if evaluation is not None:
    arrays = {f"{m}/{k}": np.asarray(v) for m, s in evaluation["scores"].items() for k, v in s.items()}
    np.savez_compressed(out / f"{prefix}scores.npz", sequence=np.asarray(evaluation["sequence"]),
                        frame=np.asarray(evaluation["frame"]), **arrays)
  (out / f"{stem}.json").write_text(json.dumps(table, indent=2) + "\n")
  (out / f"{prefix}comparisons.json").write_text(json.dumps(comparisons, indent=2) + "\n")
  text = report.format_tables(table, caption)
  if comparisons:
    text += "\n" + report.format_comparisons(comparisons)
  if validation:
    (out / "validation.json").write_text(json.dumps(validation, indent=2, default=str) + "\n")
    text += "\n" + report.format_choices(validation)
  (out / f"{stem}.md").write_text(text)
  figures.plot_comparison(images, out / f"{prefix}comparison.png")
  if logs:
    figures.plot_training_curves(logs, out / "training_curves.png")
