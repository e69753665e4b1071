"""The main job behind ``python -m experiments.train``: data, training, choices on validation, the test table.

1. Make the config's dataset (train, val and test splits) unless it exists;
   extend an existing file that lacks a split.
2. Train each variant (Ours-S, Ours) for each seed
   (``train.seed``, ``train.seed + 1``, ... ``train.seeds`` of them;
   :func:`nlosjax.train.train_model`), choosing the checkpoint on validation
   where ``train.select_checkpoint == "val"``.
3. On the **validation** split: tune every classic method
   (:func:`nlosjax.evaluation.baselines.tune`), pick the best classic
   method (validation intensity PSNR), and choose each learned variant's
   surface threshold by the same F1 rule as the classic methods'
   (:func:`nlosjax.evaluation.protocol.tune_model_thresholds`).
4. On the **test** split, once: every method, per frame; the table (mean,
   95 % interval over sequences and seeds) and the paired comparisons Ours -
   Ours-S and learned - best classic.
5. On each extra test set (``extra_test_sets``, e.g. the independent set that
   ``experiments.train`` writes), the same, with the same models and classic
   settings: ``results/table1_<name>.{md,json}``.

Writes into ``workdir``: ``config.json``, ``<variant>[-seed<k>]/{checkpoints,
metrics.jsonl, selection.json}``, and ``results/{table.md, table.json,
comparisons.json, validation.json, comparison.png, training_curves.png, scores.npz,
phases.json}`` (``scores.npz``: every method's per-frame test scores, for later comparisons;
``phases.json``: the wall seconds of each step above, :class:`Phases`).
Rerunning after an interruption resumes from the checkpoints.

With several processes (``jax.distributed.initialize`` first; ``experiments.train
--num-processes``) every process trains its share of each global batch;
process 0 alone makes the dataset, writes logs and evaluates. With
``train.check_memory`` the train steps are compiled from shapes first and the
job refuses, before any data exist, when one would not fit
(:func:`nlosjax.plan.check_fits`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import pathlib
import time

import jax

from nlosjax import files, train
from nlosjax.evaluation import baselines, protocol

__all__ = ["Phases", "model_folder", "train_and_evaluate"]


class Phases:
  """Wall seconds of the main job's steps, in the order they ran: ``with phases("dataset"): ...``.

  A name met again adds to its time (a variant's seeds are one phase each). :meth:`line`
  is the one-line summary the job prints; ``results/phases.json`` holds :meth:`record`,
  which ``benchmarks.main_job`` reads so that a change of the job's time can be placed.
  """

  def __init__(self, clock=time.perf_counter):
    self._clock, self._start = clock, clock()
    self.seconds: dict[str, float] = {}

  @contextlib.contextmanager
  def __call__(self, name: str):
    t0 = self._clock()
    try:
      yield
    finally:
      self.seconds[name] = self.seconds.get(name, 0.0) + self._clock() - t0

  def record(self) -> dict:
    """``{"phases_s": {name: seconds}, "total_s": since construction, "other_s": total - their sum}``."""
    total = self._clock() - self._start
    return {"phases_s": {k: round(v, 2) for k, v in self.seconds.items()}, "total_s": round(total, 2),
            "other_s": round(total - sum(self.seconds.values()), 2)}

  def line(self) -> str:
    r = self.record()
    parts = [f"{k} {v:.0f} s" for k, v in r["phases_s"].items()] + [f"other {r['other_s']:.0f} s"]
    return f"phases: {', '.join(parts)} ({r['total_s']:.0f} s in all)"


def model_folder(variant: str, seed: int, base_seed: int) -> str:
  """Folder of one trained model: ``variant`` for the config's own seed, else ``variant-seed<k>``."""
  return variant if seed == base_seed else f"{variant}-seed{seed}"


def _training_length(tr: train.TrainConfig) -> str:
  """How long each model trained, for the table's caption: a fixed step count or the plateau rule."""
  rule = tr.stop
  if rule.rule == "steps":
    return f"{tr.steps} steps"
  return (f"trained to a validation plateau (no gain above {rule.min_delta_db} dB over {rule.patience} "
          f"validations {rule.every} steps apart, at most {rule.max_steps} steps; each model's steps in "
          "validation.json)")


def tune_classic(config: train.RunConfig, data_path, log) -> dict:
  """Each classic method's settings chosen on ``data_path``'s validation split (``baselines.tune``)."""
  batch_size = config.train.eval_batch
  data = protocol.load_split(config, data_path, "val", batch_size=batch_size)
  data["loader"].close()
  return baselines.tune(data["measurement"], data["intensity"], data["depth"], data["setup"],
                        data["stride"], batch_size=batch_size, log=log)


def train_and_evaluate(config: train.RunConfig, workdir, *, extra_test_sets=None, log=print,
                       export: train.StateExport | None = None) -> dict:
  """Run the main job (module docstring); returns the test table ``method -> metric -> summary``.

  ``config``: the run's :class:`~nlosjax.train.RunConfig` (built from the preset by
  :meth:`~nlosjax.train.RunConfig.from_dict`); recorded in ``workdir/config.json``
  (:meth:`~nlosjax.train.RunConfig.to_dict`).

  ``export``: each model's resumable state mirrored into ``export.directory /
  <model folder>`` and resumed from there when it is ahead of ``workdir``
  (:mod:`nlosjax.train.run_state`); the data's content digest is recorded and
  checked. Past ``export.deadline`` training pauses with
  :class:`~nlosjax.train.TrainingPaused` (nothing is evaluated).

  ``extra_test_sets``: optional ``name -> path`` of further test files in the
  dataset layout (test split; no choice is made on them), each scored like
  the test split into ``results/table1_<name>.{md,json}``.
  """
  cfg, tr = config, config.train
  primary = jax.process_index() == 0
  if tr.check_memory:
    from nlosjax.plan import check_fits
    check_fits(cfg, log=log)            # before any data or parameters exist
  workdir = pathlib.Path(workdir)
  with files.writing(workdir):
    workdir.mkdir(parents=True, exist_ok=True)
  if primary:
    files.write_text_atomic(workdir / "config.json", json.dumps(cfg.to_dict(), indent=2, default=str) + "\n")
  t0 = time.perf_counter()
  phases = Phases()
  if cfg.data.path is None:
    raise ValueError("config data.path: the main job needs the dataset file's path")
  data_path = pathlib.Path(cfg.data.path)
  if primary:
    with phases("dataset"):
      train.ensure_dataset(cfg, data_path, log=log)
  if jax.process_count() > 1:              # the others wait for process 0's dataset
    from jax.experimental import multihost_utils
    multihost_utils.sync_global_devices("nlosjax dataset ready")
  n_seeds = tr.seeds
  if n_seeds < 1:
    raise ValueError(f"train.seeds must be >= 1, got {n_seeds}")
  base = tr.seed
  if export is not None and export.data_digest is None:
    from nlosjax.data.dataset import dataset_identity
    digest, fingerprint = dataset_identity(data_path)
    export = dataclasses.replace(export, data_digest=digest, data_fingerprint=fingerprint)
    log(f"dataset: content digest {export.data_digest}")
  validate = protocol.validation_scores(cfg, data_path)     # train.stop.metric decides among them
  trained, logs, checkpoints = {}, {}, {}
  for variant in tr.variants:
    for seed in range(base, base + n_seeds):
      folder = model_folder(variant, seed, base)
      seeded = dataclasses.replace(cfg, train=dataclasses.replace(tr, seed=seed))
      with phases(f"train {variant}"):
        mcfg, state = train.train_model(seeded, data_path, workdir, variant, folder=folder,
                                        validate=validate, log=log, export=export)
      trained.setdefault(variant, []).append((mcfg, train.to_host(state.params)))
      if seed == base:
        logs[variant] = train.read_metrics(workdir / folder / "metrics.jsonl")
      selection = train.read_selection(workdir / folder) or {}
      checkpoints[folder] = {"variant": variant, "seed": seed, "step": selection.get("step"),
                             "val_psnr": selection.get("val_psnr", {}),
                             **({"metric": selection["metric"], "val_score": selection["val_score"]}
                                if "metric" in selection else {}),
                             "steps_taken": selection.get("steps_taken", tr.steps),
                             "stop_reason": selection.get("stop_reason", "steps")}
  if not primary:                         # process 0 evaluates; the others are done
    return {}
  log("validation: tuning the classic methods ...")
  with phases("tune classic"):
    settings = tune_classic(cfg, data_path, log)
  best = max(settings, key=lambda m: settings[m]["psnr"])
  with phases("tune thresholds"):
    learned = protocol.tune_model_thresholds(cfg, data_path, trained, log=log)
  thresholds = {v: c["threshold"] for v, c in learned.items()}
  validation = {"split": "val", "classic": settings, "best_classic": best,
                "learned": learned, "checkpoints": checkpoints}
  with phases("test split"):
    evaluation = protocol.evaluate(cfg, data_path, trained, split="test",
                                   classic_settings=settings, model_thresholds=thresholds, log=log)
  table, comparisons = protocol.tabulate(evaluation, best_classic_method=best)
  n_frames = evaluation["n_frames"]
  n_seq = len(set(evaluation["sequence"].tolist()))
  caption = (f"Test split of `{data_path}` ({n_seq} sequences, {n_frames} frames); "
             f"{_training_length(tr)} of batch {tr.batch_size} per model, "
             f"{n_seeds} seed(s) ({base}-{base + n_seeds - 1}); "
             f"{jax.devices()[0].platform}, {jax.device_count()} device(s); "
             f"main job wall time {time.perf_counter() - t0:.0f} s.")
  with phases("write results"):
    protocol.write_results(workdir / "results", table, comparisons, evaluation["images"],
                           caption=caption, validation=validation, logs=logs, evaluation=evaluation)
  for name, path in (extra_test_sets or {}).items():
    log(f"extra test set {name}: {path} ...")
    with phases(f"test set {name}"):
      ev = protocol.evaluate(cfg, path, trained, split="test", classic_settings=settings,
                             model_thresholds=thresholds, log=log)
    t, c = protocol.tabulate(ev, best_classic_method=best)
    n_seq = len(set(ev["sequence"].tolist()))
    protocol.write_results(
        workdir / "results", t, c, ev["images"], stem=f"table1_{name}", evaluation=ev,
        caption=(f"Extra test set `{name}`: `{path}` ({n_seq} sequences, {ev['n_frames']} frames),"
                 " made by code the training data do not share; the same models (checkpoints"
                 " chosen on validation) and classic settings (tuned on validation) as the test"
                 " split. Nothing is chosen on this set."))
  log((workdir / "results" / "table.md").read_text())
  files.write_text_atomic(workdir / "results" / "phases.json", json.dumps(phases.record(), indent=2) + "\n")
  log(phases.line())
  log(f"results written to {workdir / 'results'} ({time.perf_counter() - t0:.0f} s in all)")
  return table
