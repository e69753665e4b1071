"""One run of the study (train to the plateau, score on test) and the SSM probe of a trained Ours."""

from __future__ import annotations

import json
import math
import pathlib
import time
from typing import Callable

import numpy as np

from experiments.studies.mechanisms.design import (
  LOSS_POINTS,
  PROBE,
  ROWS,
  essentials,
  run_config,
  run_dir,
  run_json,
  state_dir,
)
from experiments.studies.mechanisms.records import machine, write_json


def _subsample(rows: list[dict], n: int = LOSS_POINTS) -> list[dict]:
  """At most about ``n`` evenly spaced rows of a training log (always the last)."""
  if not rows:
    return []
  every = max(1, math.ceil(len(rows) / n))
  keep = rows[::every]
  if keep[-1] is not rows[-1]:
    keep.append(rows[-1])
  return [{k: r[k] for k in ("step", "loss", "time_s") if k in r} for r in keep]


def test_frames(config, data_path) -> tuple[np.ndarray, np.ndarray]:
  """``(sequence [N], frame [N])`` of the test split's examples in evaluation order (middle frame index).

  ``config``: the run's :class:`nlosjax.train.RunConfig`.
  """
  from nlosjax.train import make_loader
  loader = make_loader(config, data_path, "test", batch_size=config.train.eval_batch, shuffle=False, seed=0)
  try:
    batches = [loader.batch(i) for i in range(len(loader))]
  finally:
    loader.close()
  return (np.concatenate([b["sequence"] for b in batches]).astype(int),
          np.concatenate([b["frame"] for b in batches]).astype(int))


def train_and_score(cfg: dict, folder: pathlib.Path, variant: str, log: Callable[[str], None], export=None):
  """Train (or resume, or reload) one run to its plateau; returns ``(mcfg, params, test record)``.

  ``export``: a :class:`nlosjax.train.StateExport` whose folder ``model`` holds the run's
  committed state (resumed from where it is ahead of ``folder``); raises
  :class:`nlosjax.train.TrainingPaused` at its deadline.
  """
  from nlosjax import train as T
  from nlosjax.evaluation import protocol
  data_path = pathlib.Path(cfg["data"]["path"])
  typed = T.RunConfig.from_dict(cfg)
  validate = protocol.validation_psnr(typed, data_path)
  mcfg, state = T.train_model(typed, data_path, folder, variant, folder="model", validate=validate,
                              log=log, export=export)
  params = T.to_host(state.params)
  t0 = time.perf_counter()
  tuned = protocol.tune_model_thresholds(typed, data_path, {variant: [(mcfg, params)]}, log=log)[variant]
  ev = protocol.evaluate(typed, data_path, {variant: [(mcfg, params)]}, split="test", methods=(),
                         model_thresholds={variant: tuned["threshold"]}, log=log)
  sequence, frame = test_frames(typed, data_path)
  if not np.array_equal(sequence, np.asarray(ev["sequence"])):
    raise RuntimeError("the test loader's sequence order differs from protocol.evaluate's")
  test = {"split": "test", "data": str(data_path), "sequence": sequence, "frame": frame,
          "surface_threshold": tuned["threshold"], "threshold_val_f1": tuned["f1"],
          "scores": {k: np.asarray(v)[0] for k, v in ev["scores"][variant].items()},
          "eval_s": round(time.perf_counter() - t0, 1)}
  return mcfg, params, test


def run_record(cfg: dict, budget: str, row: str, seed: int, folder: pathlib.Path, test: dict) -> dict:
  """The JSON record of one finished run (module docstring)."""
  from nlosjax import train as T
  model = folder / "model"
  curve = T.read_curve(model)
  selection = T.read_selection(model) or {}
  return {"budget": budget, "row": row, "seed": seed, "variant": ROWS[row][1], "label": ROWS[row][2],
          "config": essentials(cfg), "machine": machine(),
          "steps_taken": curve["steps_taken"], "stop_reason": curve["stop_reason"],
          "best_step": curve["best_step"], "best_val_psnr": curve["best_val_psnr"],
          "train_wall_s": curve["curve"][-1]["time_s"] if curve["curve"] else None,
          "validation_curve": curve["curve"], "selection_step": selection.get("step"),
          "loss_curve": _subsample(T.read_metrics(model / "metrics.jsonl")), "test": test}


def run_one(base: dict, budget: str, row: str, seed: int, stop: dict, workdir: pathlib.Path,
            results: pathlib.Path, log: Callable[[str], None] = print, keep_loss=(),
            state: pathlib.Path | None = None, deadline: float | None = None) -> dict:
  """Train, score and (for :data:`PROBE`) probe one run; writes and returns its JSON record.

  ``state``: the root of the committed run states (:func:`state_dir`); the run's resumable
  state is exported there at every validation, with its data's digest and fingerprint, so a
  fresh clone resumes it. ``deadline`` (``time.time()``, with ``state``): pause there,
  raising :class:`nlosjax.train.TrainingPaused`.
  """
  from nlosjax import train as T
  cfg = run_config(base, budget, row, seed, stop, keep_loss)
  data_path = pathlib.Path(cfg["data"]["path"])
  T.ensure_dataset(T.RunConfig.from_dict(cfg), data_path, log=log)
  folder = run_dir(workdir, budget, row, seed)
  folder.mkdir(parents=True, exist_ok=True)
  write_json(folder / "run.json", {"budget": budget, "row": row, "seed": seed, "config": cfg})
  export = None
  if state is not None:
    from nlosjax.data.dataset import dataset_identity
    digest, fingerprint = dataset_identity(data_path)     # cached beside the data: one read per file
    export = T.StateExport(state_dir(state, budget, row, seed), data_digest=digest,
                           data_fingerprint=fingerprint, deadline=deadline)
  mcfg, params, test = train_and_score(cfg, folder, ROWS[row][1], log, export=export)
  record = run_record(cfg, budget, row, seed, folder, test)
  if (row, seed) == PROBE:
    record["probe"] = probe_model(cfg, data_path, mcfg, params, log=log)
  write_json(run_json(results, budget, row, seed), record)
  return record


def probe_model(cfg: dict, data_path, mcfg, params, log: Callable[[str], None] = print) -> dict:
  """Validation PSNR with each SSM bypassed (its output replaced by its input) and the mean gates.

  Scored as :func:`nlosjax.evaluation.protocol.validation_psnr` scores a
  checkpoint (mean over the validation frames of the clamped intensity's PSNR).
  ``intact_psnr`` is computed by that very function, so it equals the run's
  best validation PSNR bit for bit. The bypassed passes run the probe's own
  program (:func:`experiments.studies.mechanisms.probe.probed_apply`, a different XLA program,
  which may round differently in the last place, and which a process may have
  compiled under other XLA options than the validation forward it cached);
  each ``drop_db`` is measured against that program's pass with nothing
  bypassed (``probe_intact_psnr``), so an SSM the network ignores drops by
  exactly 0.

  Returns:
    ``{"split": "val", "n_frames", "intact_psnr", "probe_intact_psnr",
    "all_bypassed_psnr", "all_drop_db", "modules": [{"module", "block", "psnr",
    "drop_db", "gate_mean"}], "gates": {block: mean SiLU(z)}, "mixing": learned
    mixing weights}``; ``drop_db`` is intact minus bypassed (positive: the model
    needs that SSM).
  """
  import jax.numpy as jnp
  from tqdm import tqdm

  from experiments.studies.mechanisms import probe as P
  from nlosjax import metrics
  from nlosjax.evaluation import protocol
  from nlosjax.train import RunConfig, select_frames
  ssms, blocks = P.ssm_paths(params), P.gate_paths(params)
  fn = P.probed_apply(mcfg, ssms, blocks)
  bs = int(cfg["train"].get("eval_batch_size", cfg["train"]["batch_size"]))
  typed = RunConfig.from_dict(cfg)
  data = protocol.load_split(typed, data_path, "val", batch_size=bs)
  try:
    inputs = [select_frames(data["loader"].batch(i)["measurement"], mcfg.frames)
              for i in range(len(data["loader"]))]
  finally:
    data["loader"].close()
  masks = [("none", np.zeros(len(ssms), bool))]
  masks += [(p, np.arange(len(ssms)) == i) for i, p in enumerate(ssms)]
  masks += [("all", np.ones(len(ssms), bool))]
  psnr, gate_sums = {}, {}
  for name, mask in tqdm(masks, desc="SSM probe", unit="pass"):
    inten = []
    for x in inputs:
      out, gates = fn(params, jnp.asarray(x), jnp.asarray(mask))
      inten.append(np.clip(np.asarray(out["intensity"]), 0.0, 1.0))
      if name == "none":
        for block, v in gates.items():
          gate_sums[block] = gate_sums.get(block, 0.0) + np.asarray(v, np.float64)
    psnr[name] = float(np.mean(np.asarray(metrics.psnr(np.concatenate(inten), data["intensity"]))))
  gates = {b: float(s[0] / s[1]) for b, s in gate_sums.items()}
  modules = []
  for p in ssms:
    block = next((b for b in blocks if p.startswith(b + "/")), None)
    modules.append({"module": p, "block": block, "psnr": psnr[p], "drop_db": psnr["none"] - psnr[p],
                    "gate_mean": gates.get(block)})
  log(f"[probe] intact {psnr['none']:.2f} dB; every SSM bypassed {psnr['all']:.2f} dB")
  intact = protocol.validation_psnr(typed, data_path)(mcfg, params)
  return {"split": "val", "n_frames": int(len(data["intensity"])), "intact_psnr": intact,
          "probe_intact_psnr": psnr["none"],
          "all_bypassed_psnr": psnr["all"], "all_drop_db": psnr["none"] - psnr["all"],
          "modules": modules, "gates": gates, "mixing": P.mixing_weights(params)}


def probe_run_dir(folder: pathlib.Path, results: pathlib.Path, log: Callable[[str], None] = print) -> dict:
  """``--probe RUN_DIR``: probe a finished run's best model; stored in its JSON when that exists."""
  from nlosjax import train as T
  from nlosjax.evaluation import protocol
  folder = pathlib.Path(folder)
  meta_path = folder / "run.json"
  if not meta_path.exists():
    raise SystemExit(f"--probe: {folder} is not a run folder of this benchmark (no run.json)")
  meta = json.loads(meta_path.read_text())
  selection = T.read_selection(folder / "model") or {}
  if "stop_reason" not in selection:
    raise SystemExit(f"--probe: the run in {folder} has not finished (no stop reason in "
                     "model/selection.json); run the study first")
  cfg = meta["config"]
  data_path = pathlib.Path(cfg["data"]["path"])
  variant = ROWS[meta["row"]][1]
  typed = T.RunConfig.from_dict(cfg)
  mcfg, state = T.train_model(typed, data_path, folder, variant, folder="model",
                              validate=protocol.validation_psnr(typed, data_path), log=log)
  result = probe_model(cfg, data_path, mcfg, T.to_host(state.params), log=log)
  path = run_json(results, meta["budget"], meta["row"], int(meta["seed"]))
  if path.exists():
    record = json.loads(path.read_text())
    record["probe"] = result
    write_json(path, record)
    log(f"[probe] written into {path}")
  return result
