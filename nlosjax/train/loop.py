"""The training loop of one variant and one seed (:func:`train_model`), and the config pieces it reads.

Resumable (the latest checkpoint and the data position), data-parallel over
the run's mesh, and multi-process: each process reads only its rows of every
global batch; process 0 writes the log and the selection.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import pathlib
import time
from typing import TYPE_CHECKING, Any, Callable

import jax
import numpy as np

from nlosjax import losses
from nlosjax.train.checkpoint import Checkpointer, run_signature
from nlosjax.train.config import BASELINES, RunConfig, model_class
from nlosjax.train.optimizer import OptimConfig, learning_rate_at, make_optimizer
from nlosjax.train.run_state import StateExport, TrainingPaused, copy_logs, export_state, import_state, read_meta
from nlosjax.train.sharding import mesh_for, shard_batch, to_host
from nlosjax.train.state import TrainState, create_train_state, network
from nlosjax.train.step import BATCH_KEYS, make_train_step
from nlosjax.train.stopping import BEST_FOLDER, PlateauTracker
from nlosjax.variants import USM, VARIANTS

if TYPE_CHECKING:
  from nlosjax.data.dataset import TripletLoader

#: Input frames of each variant (:data:`nlosjax.variants.VARIANTS`).
VARIANT_FRAMES = {name: v.frames for name, v in VARIANTS.items()}


def model_config_for(config: RunConfig, setup, variant: str):
  """The model config of ``variant`` for a dataset's Setup.

  ``"ours"`` / ``"ours_s"``: a :class:`~nlosjax.models.network.ModelConfig` from
  the config's ``model`` section; ``"usm"``, ``"lfe"``, ``"ik"``: their
  :class:`~nlosjax.models.usm.USMConfig`, :class:`~nlosjax.models.lfe.LFEConfig`,
  :class:`~nlosjax.models.ik.IKConfig` from their own section's ``model`` (published
  widths where absent). The baselines' phasor-field loss wavelet (``wavelet_cycles``,
  ``wavelet_sampling``) is Ours' unless their own ``model`` section sets it, so all
  train with the same loss (and a preset that needs a longer wavelet for its
  bins, as ``real``, gives USM one too).
  """
  if variant not in VARIANT_FRAMES:
    raise ValueError(f"variant must be one of {tuple(VARIANT_FRAMES)}, got {variant!r}")
  cls = model_class(variant)
  if variant in BASELINES:
    baseline = dict(config.baselines[variant].model)
    for key in ("wavelet_cycles", "wavelet_sampling"):
      if key in config.model:
        baseline.setdefault(key, config.model[key])
    return cls(setup=setup, stride=config.data.stride(), **baseline)
  return cls(setup=setup, stride=config.data.stride(), **{**config.model, "frames": VARIANT_FRAMES[variant]})


def select_frames(measurement: np.ndarray, frames: int) -> np.ndarray:
  """``[B, 3, T, h, w] -> [B, frames, T, h, w]`` centred on the middle frame."""
  mid = measurement.shape[1] // 2
  return measurement[:, mid - frames // 2:mid + frames // 2 + 1]


def make_loader(config: RunConfig, path, split: str, *, batch_size: int, shuffle: bool, seed: int,
                shard: tuple[int, int] = (0, 1), window: int = 3):
  """The config's :class:`~nlosjax.data.dataset.TripletLoader` of ``split`` (the model's under-scan offset checked).

  ``data.loader`` is :class:`~nlosjax.data.dataset.LoaderOptions` (its ``prefetch`` is the
  training loop's: :func:`train_model`). ``shard = (index, count)``: this process's rows of
  every global batch. ``window``: input frames per example (odd; 3 is the triplet every
  variant reads, a wider one serves a network of more frames).
  """
  from nlosjax.data.dataset import TripletLoader
  data = config.data
  opts = data.loader
  return TripletLoader(path, split=split, batch_size=batch_size, stride=data.stride(), offset=data.input_offset,
                       seed=seed, shuffle=shuffle, drop_remainder=shuffle,
                       ends=opts.ends, target=opts.target, in_memory=opts.in_memory,
                       prefetch_size=opts.prefetch, shard=shard, window=window)


def ensure_dataset(config: RunConfig, path: pathlib.Path, log: Callable[[str], None] = print) -> None:
  """Generate the config's dataset at ``path``, or add the sequences an existing file lacks.

  An existing file made with the same data configuration but fewer sequences
  (e.g. before the validation split existed) is extended in place, keeping
  every stored sequence (:func:`~nlosjax.data.dataset.extend_dataset`).

  Raises:
    ValueError: ``path`` holds a dataset of another data configuration or generator
      version (the message names what differs), or more sequences of a split than the
      config asks for: training on it would not be training on the config's data.
  """
  from nlosjax.data.dataset import extend_dataset, write_dataset
  path = pathlib.Path(path)
  spec = config.data.spec()
  workers = config.train.data_workers
  if path.exists():
    result = extend_dataset(path, spec, workers=workers)
    log(f"dataset: using {path}" + (f" (added {result.generated} sequences the config asks for)"
                                    if result.generated else ""))
    return
  log(f"dataset: generating {path} ...")
  t0 = time.perf_counter()
  write_dataset(path, spec, workers=workers)
  log(f"dataset: done in {time.perf_counter() - t0:.0f} s")


def read_metrics(path) -> list[dict]:
  """Rows of a ``metrics.jsonl`` training log (``[]`` if absent; stops at a line cut by a kill)."""
  path = pathlib.Path(path)
  if not path.exists():
    return []
  rows = []
  for line in path.read_text().splitlines():
    try:
      rows.append(json.loads(line))
    except json.JSONDecodeError:       # a line cut by a kill
      break
  return rows


def train_model(config: RunConfig, data_path, workdir, variant: str, *, folder: str | None = None,
                validate: Callable[[Any, Any], float] | None = None,
                log: Callable[[str], None] = print,
                export: StateExport | None = None, loader: TripletLoader | None = None,
                model_config: Any = None) -> tuple[Any, TrainState]:
  """Train one variant (a name of :data:`nlosjax.variants.VARIANTS`), resuming from ``workdir/<folder>``.

  Args:
    config: the run config (a :class:`~nlosjax.train.config.RunConfig`);
      the seed is ``train.seed``.
    data_path: the dataset file.
    workdir: the run folder.
    variant: a name of :data:`nlosjax.variants.VARIANTS`.
    folder: sub-folder of this model (default ``variant``).
    validate: ``(model_config, params) -> score`` on the validation split
      (higher is better; the validation intensity PSNR in dB). With
      ``train.select_checkpoint == "val"`` every kept checkpoint
      is scored after training and the best is returned; the scores and the
      choice go to ``<folder>/selection.json`` (:func:`read_selection`).
      Required by the plateau stopping rule (``train.stop``,
      :mod:`nlosjax.train.stopping`), which scores the model every
      ``stop.every`` steps during training, stops when the scores stop
      improving (or at ``stop.max_steps``) and returns the best; its curve
      goes to ``<folder>/validation_curve.json``, the steps taken and the stop
      reason to ``selection.json`` too. A rerun of a stopped run trains nothing.
    log: progress messages.
    export: where the run's resumable state is mirrored at every checkpoint
      (:class:`~nlosjax.train.run_state.StateExport`, folder ``export.directory /
      <folder>``): resumed from when it is ahead of ``workdir`` (a fresh clone or
      machine), refused when trained under another signature or data digest; past
      ``export.deadline`` the run saves, exports and raises
      :class:`~nlosjax.train.run_state.TrainingPaused`.
    loader: the training batches (default: :func:`make_loader` of ``data_path``'s train
      split, the config's loader options, batch ``train.batch_size``, seed ``train.seed``):
      any :class:`~nlosjax.data.dataset.TripletLoader` (its subclasses choose other frames);
      ``data_path`` is then unused. Closed when training ends, returns or raises. Several processes need
      one sharded loader each (``shard``, as :func:`make_loader` builds).
    model_config: the network to train (default :func:`model_config_for` the variant
      on the loader's Setup); ``variant`` still names the training recipe
      (:func:`training_recipe`) and labels progress.
  Returns:
    ``(model_config, state)``: after ``train.steps`` steps, or at
    the checkpoint chosen on validation (the plateau rule's best).
  """
  from tqdm import tqdm

  from nlosjax.models.network import format_summary, model_summary
  tr = config.train
  steps, batch_size, seed = tr.steps, tr.batch_size, tr.seed
  stop = tr.stop
  if stop.rule == "plateau" and validate is None:
    raise ValueError('train.stop.rule "plateau" needs the validate callback')
  steps = stop.horizon(steps)       # the plateau rule: its max_steps, also the schedule's horizon
  label = folder or variant              # the model's folder, and its name in logs and progress bars
  vdir = pathlib.Path(workdir) / label
  vdir.mkdir(parents=True, exist_ok=True)
  primary = jax.process_index() == 0
  if not primary:
    log = lambda s: None                                 # noqa: E731 -- one process reports
  if loader is None:
    loader = make_loader(config, data_path, "train", batch_size=batch_size, shuffle=True, seed=seed,
                         shard=(jax.process_index(), jax.process_count()))
  try:                                  # the loader is closed however training ends
    mcfg = model_config_for(config, loader.setup, variant) if model_config is None else model_config
    log(f"[{label}] " + format_summary(model_summary(mcfg)).replace("\n", f"\n[{label}] "))
    model = network(mcfg)
    optim, weights = training_recipe(config, variant)
    mesh = mesh_for(config)
    key = jax.random.key(seed)
    init_key, loop_key = jax.random.split(key)
    del key
    shape = (batch_size, mcfg.frames, loader.setup.num_bins) + tuple(loader.input_shape[-2:])
    state = create_train_state(model, shape, make_optimizer(optim, steps), init_key, mesh)
    signature = run_signature(mcfg, state.params, optim, weights, batch_size, seed)
    ckpt = Checkpointer(vdir / "checkpoints", signature, every=tr.checkpoint_every,
                        keep=tr.keep_checkpoints, model=mcfg)
    start = 0
    restored = ckpt.restore_latest(state)
    if restored is not None:
      state, start = restored
      log(f"[{label}] resumed from step {start} ({ckpt.directory})")
    imported_best = None
    exported = read_meta(export.folder(label)) if export is not None else None
    finished = bool(exported and exported.get("finished"))   # its chosen parameters alone: no more training
    if exported is not None and exported["step"] > start and primary:
      state, imported_best, meta = import_state(export.folder(label), state, signature=signature, model=mcfg,
                                                data_digest=export.data_digest,
                                                data_fingerprint=export.data_fingerprint,
                                                allow_data_change=export.allow_data_change)
      start = int(state.step)
      copy_logs(export.folder(label), vdir)
      if finished and int(imported_best.step) != start:   # where the run's selection names it
        ckpt.save(imported_best, int(imported_best.step), force=True)
      ckpt.save(state, start, force=True)
      ckpt.wait()
      log(f"[{label}] resumed from step {start} of the exported state {export.folder(label)}"
          f"{meta['data_check'].describe()}" + (" (finished: its chosen parameters)" if finished else ""))
    elif exported is not None and exported["step"] > start:
      raise ValueError("resuming from an exported state needs a single process; resume once with one, "
                       "then continue with several")
    tracker = None
    if stop.rule == "plateau":
      best = Checkpointer(vdir / BEST_FOLDER, signature, every=1, keep=1, model=mcfg)
      if imported_best is not None and int(imported_best.step) not in best.all_steps():
        best.save(imported_best, int(imported_best.step), force=True)
        best.wait()
      tracker = PlateauTracker(vdir, stop, best, validate, lambda s: learning_rate_at(optim, steps, s - 1),
                               primary=primary)
      tracker.resume(start)
      if tracker.pending(start):       # killed after the checkpoint of a validation step, before its curve
        tracker.record(mcfg, state, start, to_host)
    if finished and (tracker.reason(start) is None if tracker is not None else start < steps):
      raise ValueError(f"[{label}] {export.folder(label)} holds a finished run's chosen parameters only "
                       f"(step {exported['step']}), and this config trains it further; train from its "
                       "workdir, or from the export an earlier commit holds")
    # One process writes the log (several processes share the workdir); the others write
    # theirs to /dev/null.
    log_path = vdir / "metrics.jsonl" if primary else pathlib.Path(os.devnull)
    if primary:
      kept = [r for r in read_metrics(log_path) if r["step"] <= start]
      log_path.write_text("".join(json.dumps(r) + "\n" for r in kept))
    step_fn = make_train_step(mcfg, weights, mesh)
    log_every = tr.log_every
    exported_best = {"step": (exported or {}).get("best_step")}

    def export_now(current: TrainState, chosen: TrainState | None = None) -> None:
      """Mirror ``current``, just checkpointed, into the export folder (primary process); ``chosen``:
      the run has finished with this state, and the export keeps its parameters alone."""
      if export is None or not primary:
        return
      if chosen is not None:
        export_state(export.folder(label), vdir, to_host(current), signature=signature,
                     best_step=tracker.best_step if tracker is not None else None,
                     data_digest=export.data_digest, data_fingerprint=export.data_fingerprint,
                     chosen=to_host(chosen))
        return
      best_step = tracker.best_step if tracker is not None else None
      best_state = None
      if best_step is not None and best_step != exported_best["step"]:
        best_state = current if best_step == int(current.step) else tracker.best_state(current)
      export_state(export.folder(label), vdir, to_host(current), signature=signature,
                   best=None if best_state is None else to_host(best_state),
                   best_step=best_step, data_digest=export.data_digest,
                   data_fingerprint=export.data_fingerprint)
      exported_best["step"] = best_step

    t_start = time.perf_counter()
    # Batches are a function of the step; with data.loader.prefetch they are read that many
    # steps ahead in a thread while the step runs (the same batches).
    with open(log_path, "a") as f, tqdm(total=steps, initial=start, desc=f"train {label}",
                                        unit="step", dynamic_ncols=True, mininterval=2.0,
                                        disable=not primary) as bar, \
         contextlib.closing(loader.iterate(start, max(0, steps - start))) as batches:
      for step in range(start, steps):
        if tracker is not None and tracker.reason(step):
          break                           # a stopped run (rerun after its end): no step more
        host = next(batches)
        batch = {k: host[k] for k in BATCH_KEYS}
        batch["measurement"] = select_frames(batch["measurement"], mcfg.frames)
        state, metrics = step_fn(state, shard_batch(batch, mesh), jax.random.fold_in(loop_key, step))
        done = step + 1
        validating = tracker is not None and stop.validates_at(done)
        if done % log_every == 0 or done == steps or validating:
          m = {k: float(v) for k, v in to_host(metrics).items()}
          if not all(math.isfinite(v) for v in m.values()):
            raise FloatingPointError(f"[{label}] non-finite metrics at step {done}: {m}")
          row = {"step": done, "time_s": round(time.perf_counter() - t_start, 3), **m}
          f.write(json.dumps(row) + "\n")
          f.flush()
          bar.set_postfix(loss=f"{m['loss']:.4f}")
        pause = export is not None and export.past_deadline() and done < steps
        if validating:
          ckpt.save(state, done, force=True)
          ckpt.wait()                     # the curve may name only finished checkpoints
          score = tracker.record(mcfg, state, done, to_host)
          export_now(state)
          bar.set_postfix(**{f"val_{stop.metric}": f"{score:.2f}"})
          bar.update(1)
          if tracker.reason(done):
            break
        else:
          if ckpt.save(state, done, force=(done == steps) or pause):
            export_now(state)
          bar.update(1)
        if pause and not (tracker is not None and tracker.reason(done)):
          batches.close()
          ckpt.close()
          if tracker is not None:
            tracker.best.close()
          log(f"[{label}] paused at step {done} (deadline); state exported to {export.folder(label)}")
          raise TrainingPaused(variant, done, export.folder(label))
    batches.close()
    loader.close()
    if tracker is not None:
      chosen = _finish_plateau(tracker, state, ckpt, vdir, label, primary, log)
      if not (finished and imported_best is not None):   # an export read back finished is left as it was
        export_now(state, chosen)         # the chosen parameters, the final curve and selection.json
      return mcfg, chosen
    if finished and imported_best is not None:   # selected when it trained; selection.json came with it
      ckpt.close()
      return mcfg, imported_best
    last = state
    selection = {"select": tr.select_checkpoint, "step": int(state.step), "val_psnr": {}}
    if selection["select"] == "val" and validate is not None:
      candidates, deciding, every = {}, {}, {}
      for step in ckpt.all_steps():
        candidate, _ = ckpt.restore(state, step)
        deciding[step], every[step] = stop.score(validate(mcfg, to_host(candidate.params)))
        selection["val_psnr"][step] = every[step].get("psnr", deciding[step])
        candidates[step] = candidate
      if stop.metric != "psnr":
        selection.update(metric=stop.metric, val_score=deciding)
      if any(len(v) > 1 for v in every.values()):
        selection["val"] = every               # every score of every kept step, for a later look
      best = max(deciding, key=lambda k: (deciding[k], k))
      state = candidates[best]
      selection["step"] = int(best)
      log(f"[{label}] checkpoint chosen on validation {stop.metric}: step {best} "
          f"({', '.join(f'{k}: {v:.2f} dB' for k, v in deciding.items())})")
    ckpt.close()
    if primary:
      (vdir / "selection.json").write_text(json.dumps(selection, indent=2) + "\n")
    export_now(last, state)               # the selected parameters, with selection.json
    return mcfg, state
  finally:
    loader.close()


def _finish_plateau(tracker: PlateauTracker, state: TrainState, ckpt: Checkpointer, vdir: pathlib.Path,
                    label: str, primary: bool, log: Callable[[str], None]) -> TrainState:
  """End a plateau run: the best state, the final curve and ``selection.json``."""
  done = tracker.curve[-1]["step"] if tracker.curve else int(state.step)
  reason = tracker.reason(done)
  if reason is None:
    raise RuntimeError(f"[{label}] the plateau run ended at step {done} without a stop reason")
  best = tracker.best_state(state)
  ckpt.close()
  tracker.best.close()
  tracker.write(done)
  summary = tracker.summary(done)
  selection = {"select": "plateau", "step": int(best.step), "steps_taken": int(done),
               "stop_reason": reason, "rule": tracker.rule.to_dict(),
               "val_psnr": {p["step"]: p["val_psnr"] for p in tracker.curve}}
  if tracker.rule.metric != "psnr":
    selection.update(metric=tracker.rule.metric,
                     val_score={p["step"]: s for p, s in zip(tracker.curve, tracker.scores)})
  if primary:
    (vdir / "selection.json").write_text(json.dumps(selection, indent=2) + "\n")
  log(f"[{label}] stopped after {done} steps ({reason}); best on validation {tracker.rule.metric}: step "
      f"{int(best.step)} ({summary.get('best_score', summary['best_val_psnr']):.2f} dB)")
  return best


def training_recipe(config: RunConfig, variant: str) -> tuple[OptimConfig, losses.LossWeights]:
  """``(optimiser, loss weights)`` a variant trains with.

  The config's ``train.optim`` and ``train.loss``, except for the baselines: USM with
  ``usm.recipe == "published"`` (:data:`USM_RECIPES`) trains with its published AdamW
  (lr 1e-4, weight decay 1e-4, no schedule, no clipping) and loss; with ``"ours"`` (and LFE
  and I-K always) with Ours' recipe, its own section's ``optim`` entries (e.g. its own
  learning rate, chosen on validation) replacing ``train.optim``'s.
  """
  optim = config.train.optim
  if variant in BASELINES:
    section = config.baselines[variant]
    if variant == USM and section.recipe == "published":
      from nlosjax.models.usm import PUBLISHED_LOSS, PUBLISHED_OPTIM
      return OptimConfig(**PUBLISHED_OPTIM), losses.LossWeights(**PUBLISHED_LOSS)
    optim = dataclasses.replace(optim, **section.optim)   # LFE's, I-K's "transient" is their input
  return optim, config.train.loss


def read_selection(folder) -> dict | None:
  """A model folder's ``selection.json`` (written by :func:`train_model`), or None.

  ``{"select": "last" | "val" | "plateau", "step": chosen step, "val_psnr": {step: dB}}``, and
  where the rule decides on another score (``train.stop.metric``) ``"metric"`` and
  ``"val_score": {step: dB}``;
  a plateau run adds ``"steps_taken"``, ``"stop_reason"`` (``"plateau"`` or
  ``"max_steps"``) and ``"rule"`` (its curve with times: ``validation_curve.json``,
  :func:`nlosjax.train.stopping.read_curve`).
  """
  path = pathlib.Path(folder) / "selection.json"
  if not path.exists():
    return None
  d = json.loads(path.read_text())
  d["val_psnr"] = {int(k): v for k, v in d.get("val_psnr", {}).items()}
  if "val_score" in d:
    d["val_score"] = {int(k): v for k, v in d["val_score"].items()}
  return d
