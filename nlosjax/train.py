"""Training of ST-Mamba: optimiser, state, one pure train step, checkpoints, the training loop.

The pieces, each usable alone:

* :func:`create_train_state` -- parameters from ``jax.eval_shape`` first (count,
  shape errors before any allocation), then ``init`` jitted with replicated
  output sharding; optax AdamW with optional warm-up + cosine and clipping.
* :func:`train_step` -- ``(state, batch, key) -> (state, metrics)``, pure; jitted
  by :func:`make_train_step` with the state donated and the batch sharded over
  a ``Mesh`` of every device (data parallel; the same code on 1 CPU, several
  GPUs, or several hosts after ``jax.distributed.initialize``).
* :class:`Checkpointer` -- orbax ``CheckpointManager`` saving params, optimizer
  state, step and the data position; restores the latest automatically and
  refuses a checkpoint written by another model config.
* :func:`train_model` -- the loop: one variant, one seed, resumable.

Evaluation (classic baselines, scores, tables, figures) is
:mod:`nlosjax.evaluation`; the main job behind ``python -m experiments.train``
is :func:`nlosjax.main_job.train_and_evaluate`.

Batches are dicts of arrays: ``measurement [B, F, T, h, w]`` (under-scanned
noisy counts of ``F`` adjacent frames), ``transient [B, T, H, W]`` (clean
full-grid transient of the middle frame), ``intensity [B, H, W]`` in [0, 1],
``depth [B, H, W]`` metres.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import os
import pathlib
import time
from typing import Any, Callable

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax.training import train_state
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from nlosjax import losses
from nlosjax.physics import illumination_wavelet

BATCH_KEYS = ("measurement", "transient", "intensity", "depth")


# ------------------------------------------------------------------ config
@dataclasses.dataclass(frozen=True)
class OptimConfig:
  """Optimiser settings (AdamW, paper Sec. 5.1).

  Attributes:
    learning_rate: peak learning rate (paper 1e-4).
    weight_decay: decoupled weight decay. The paper prints 0.95; its
      predecessor USM used 1e-4 (see ``benchmarks/results/table2.md`` for the
      measured comparison behind our default).
    warmup_steps: linear warm-up from 0 (0: none).
    cosine: decay to ``end_fraction * learning_rate`` by the last step.
    end_fraction: final learning rate as a fraction of the peak.
    clip_norm: global gradient-norm clipping (None: none).
    b1, b2: Adam moments.
  """

  learning_rate: float = 1e-4
  weight_decay: float = 1e-4
  warmup_steps: int = 0
  cosine: bool = False
  end_fraction: float = 0.1
  clip_norm: float | None = 1.0
  b1: float = 0.9
  b2: float = 0.999


@functools.lru_cache(maxsize=16)
def make_optimizer(cfg: OptimConfig, total_steps: int) -> optax.GradientTransformation:
  """AdamW with the configured schedule and clipping.

  Cached: the same settings give the same object, so train states built for
  several seeds share one static ``tx`` and one compiled train step.
  """
  if not cfg.learning_rate > 0:
    raise ValueError(f"learning_rate must be > 0, got {cfg.learning_rate!r}")
  if not cfg.weight_decay >= 0:
    raise ValueError(f"weight_decay must be >= 0, got {cfg.weight_decay!r}")
  lr: Any = cfg.learning_rate
  if cfg.cosine:
    lr = optax.warmup_cosine_decay_schedule(
        0.0, cfg.learning_rate, max(cfg.warmup_steps, 1), max(total_steps, cfg.warmup_steps + 1),
        end_value=cfg.learning_rate * cfg.end_fraction)
  elif cfg.warmup_steps:
    lr = optax.join_schedules([optax.linear_schedule(0.0, cfg.learning_rate, cfg.warmup_steps),
                               optax.constant_schedule(cfg.learning_rate)], [cfg.warmup_steps])
  parts = []
  if cfg.clip_norm:
    parts.append(optax.clip_by_global_norm(cfg.clip_norm))
  parts.append(optax.adamw(lr, b1=cfg.b1, b2=cfg.b2, weight_decay=cfg.weight_decay))
  return optax.chain(*parts)


class TrainState(train_state.TrainState):
  """flax ``TrainState``: ``step`` (int32 ``[]``), ``params``, ``opt_state``; ``apply_fn``, ``tx`` static."""


def create_train_state(model: nn.Module, input_shape: tuple[int, ...], tx, key: jax.Array,
                       mesh: Mesh | None = None) -> TrainState:
  """Initialise parameters and optimiser state, replicated over ``mesh``.

  Shapes are traced with ``jax.eval_shape`` first, so a config error shows
  before anything is allocated.

  Args:
    model: the Flax module (e.g. ``STMambaNet(config)``).
    input_shape: ``[B, F, T, h, w]`` of one batch.
    tx: the optax transformation.
    key: PRNG key for the parameters.
    mesh: devices to replicate over (default: every device).
  """
  mesh = mesh or make_mesh()
  init = _jitted_init(model, tuple(input_shape), tx, mesh)
  return init(key, jnp.zeros(tuple(input_shape), jnp.float32))


@functools.lru_cache(maxsize=8)
def _jitted_init(model: nn.Module, input_shape: tuple[int, ...], tx, mesh: Mesh) -> Callable:
  """``init(key, x) -> TrainState`` jitted, one per (model, shape, optimiser, mesh).

  Compiling it costs about as much as a forward pass (tens of seconds on
  CPU), so the seeds of one run share it: pass the same ``model`` instance
  (:func:`network`) and optimiser (:func:`make_optimizer` is cached).
  """
  def init(k, x):
    params = model.init(k, x)["params"]
    return TrainState.create(apply_fn=model.apply, params=params, tx=tx)

  abstract = jax.eval_shape(init, jax.random.key(0), jax.ShapeDtypeStruct(input_shape, jnp.float32))
  replicated = jax.tree.map(lambda _: NamedSharding(mesh, P()), abstract)
  return jax.jit(init, out_shardings=replicated)


@functools.lru_cache(maxsize=8)
def network(model_config) -> nn.Module:
  """The module of ``model_config`` (``STMambaNet`` or ``USMNet``: ``model_config.module()``), one instance per config.

  A ``TrainState`` holds ``model.apply``, a bound method, and bound methods
  compare by the identity of their module: one instance per config lets the
  seeds and resumed runs of one process reuse the compiled init and train
  step instead of compiling them again.
  """
  return model_config.module()


# ------------------------------------------------------------------ step
def make_targets(batch: dict, time_window: tuple[int, int]) -> dict:
  """Loss targets in the model's units.

  The model predicts the transient's shape, not its photon scale (which
  depends on efficiency and exposure): the clean target is divided by its
  own root-mean-square over the model's time window (guarded against 0).
  """
  a, b = time_window
  clean = batch["transient"].astype(jnp.float32)
  rms = jnp.sqrt(jnp.mean(jnp.square(clean[:, a:b]), axis=(1, 2, 3)))
  clean = clean / jnp.where(rms > 0, rms, 1.0)[:, None, None, None]
  return {"transient": clean, "intensity": batch["intensity"].astype(jnp.float32),
          "depth": batch["depth"].astype(jnp.float32)}


def train_step(state: TrainState, batch: dict, key: jax.Array, *, weights: losses.LossWeights,
               wavelet, time_window: tuple[int, int]) -> tuple[TrainState, dict]:
  """One AdamW step on the paper's loss; pure.

  Args:
    state: the train state.
    batch: see the module docstring.
    key: this step's PRNG key (``fold_in(loop_key, step)``). The model is
      deterministic; the key is part of the signature for stochastic layers
      and augmentation.
    weights, wavelet, time_window: static loss settings.
  Returns:
    ``(new_state, metrics)``; metrics: ``loss``, every loss term, and
    ``l2_grads``, ``l2_params``, ``l2_updates``.
  """
  del key

  def loss_fn(params):
    out = state.apply_fn({"params": params}, batch["measurement"])
    targets = make_targets(batch, time_window)
    return losses.total_loss(out, targets, weights, wavelet)

  (loss, terms), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
  new_state = state.apply_gradients(grads=grads)
  updates = jax.tree.map(lambda a, b: a - b, new_state.params, state.params)
  metrics = {"loss": loss, **terms, "l2_grads": optax.tree.norm(grads),
             "l2_params": optax.tree.norm(new_state.params),
             "l2_updates": optax.tree.norm(updates)}
  return new_state, metrics


def initialize_distributed(coordinator: str, num_processes: int, process_id: int) -> None:
  """Join a multi-process run (``jax.distributed.initialize``) before any device is used.

  On CPU the cross-process collectives use gloo (XLA:CPU has no default
  implementation), so the same command runs on a laptop, a CPU cluster or
  GPUs. Each process then sees every process's devices in ``jax.devices()``.
  """
  if num_processes < 1 or not 0 <= process_id < num_processes:
    raise ValueError(f"need 0 <= process_id < num_processes, got {process_id} of {num_processes}")
  if num_processes == 1:
    return
  try:
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
  except (AttributeError, ValueError):   # an older JAX without the option
    pass
  jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes,
                             process_id=process_id)


def make_mesh(devices=None) -> Mesh:
  """A 1D ``Mesh`` named ``"data"`` over ``devices`` (default: every device of every host)."""
  devices = np.asarray(devices if devices is not None else jax.devices())
  return Mesh(devices.reshape(-1), ("data",))


def mesh_for(config: dict) -> Mesh:
  """The data-parallel mesh of a run: every device, or the first ``config["train"]["devices"]``.

  With several processes (``jax.distributed``) the mesh spans every process's
  devices and ``train.devices`` must be None.
  """
  n = config.get("train", {}).get("devices")
  if n is None:
    return make_mesh()
  n = int(n)
  if jax.process_count() > 1:
    raise ValueError("train.devices selects devices of one process; leave it None with jax.distributed")
  if not 1 <= n <= jax.device_count():
    raise ValueError(f"train.devices = {n}, but this process has {jax.device_count()} device(s)")
  return make_mesh(jax.devices()[:n])


def to_host(tree):
  """Fully replicated (global) arrays as NumPy on this host; works with several processes too."""
  def one(x):
    if isinstance(x, jax.Array) and not x.is_fully_addressable:
      if not x.is_fully_replicated:
        raise ValueError("to_host needs fully replicated arrays across processes")
      return np.asarray(x.addressable_data(0))
    return np.asarray(x)
  return jax.tree.map(one, tree)


def shard_batch(batch: dict, mesh: Mesh) -> dict:
  """Place a host batch on the mesh, split along axis 0 (the batch must divide evenly).

  With several processes each passes its own rows (``TripletLoader(shard=...)``):
  the global batch is their concatenation in process order.
  """
  n = mesh.devices.size
  sharding = NamedSharding(mesh, P("data"))
  out = {}
  for k, v in batch.items():
    v = np.asarray(v)
    if jax.process_count() > 1:
      out[k] = jax.make_array_from_process_local_data(sharding, v)
      continue
    if v.shape[0] % n:
      raise ValueError(f"batch size {v.shape[0]} of {k!r} is not divisible by the {n} devices")
    out[k] = jax.device_put(v, sharding)
  return out


@functools.lru_cache(maxsize=8)
def make_train_step(model_config, weights: losses.LossWeights, mesh: Mesh) -> Callable:
  """``train_step`` jitted: state donated and replicated, batch sharded over ``mesh``.

  Cached per (model config, weights, mesh), so a resumed or repeated run in
  one process reuses the compiled step.
  """
  wavelet = (illumination_wavelet(model_config.setup, cycles=model_config.wavelet_cycles,
                                  sampling_coeff=model_config.wavelet_sampling)
             if weights.phasor_field else None)
  fn = functools.partial(train_step, weights=weights, wavelet=wavelet,
                         time_window=model_config.time_window)
  replicated = NamedSharding(mesh, P())
  return jax.jit(fn, donate_argnums=0, out_shardings=(replicated, replicated))


# ------------------------------------------------------------ checkpoints
class Checkpointer:
  """orbax ``CheckpointManager`` for a :class:`TrainState` plus JSON metadata.

  Each save writes ``{"params", "opt_state", "step"}`` (``StandardSave``) and
  ``{"data_position", "model_config"}`` (``JsonSave``) to a new step folder;
  orbax finalises a folder atomically, so a kill mid-save leaves the previous
  checkpoints intact. :meth:`restore_latest` refuses a checkpoint whose model
  config differs, and reports a corrupt one by name; it never deletes.

  Args:
    directory: the checkpoint folder (created).
    model_config: a description of the model (``repr`` of its config) that
      must match on restore.
    every: save interval in steps.
    keep: checkpoints kept.
  """

  def __init__(self, directory, model_config: str, *, every: int, keep: int = 2):
    import orbax.checkpoint as ocp
    self._ocp = ocp
    self.directory = pathlib.Path(directory).absolute()
    self.model_config = model_config
    self.every = int(every)
    options = ocp.CheckpointManagerOptions(max_to_keep=keep, save_interval_steps=1, create=True)
    self.manager = ocp.CheckpointManager(self.directory, options=options)

  def latest_step(self) -> int | None:
    return self.manager.latest_step()

  def save(self, state: TrainState, data_position: int, *, force: bool = False) -> bool:
    step = int(state.step)
    if not force and (step % self.every):
      return False
    ocp = self._ocp
    item = {"params": state.params, "opt_state": state.opt_state, "step": state.step}
    meta = {"data_position": int(data_position), "model_config": self.model_config}
    self.manager.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(item),
                                                     meta=ocp.args.JsonSave(meta)), force=force)
    return True

  def all_steps(self) -> list[int]:
    """Steps of the kept checkpoints, ascending."""
    return sorted(self.manager.all_steps())

  def restore_latest(self, state: TrainState) -> tuple[TrainState, int] | None:
    """``(state, data_position)`` from the latest checkpoint, or None when there is none."""
    step = self.latest_step()
    if step is None:
      return None
    return self.restore(state, step)

  def restore(self, state: TrainState, step: int) -> tuple[TrainState, int]:
    """``(state, data_position)`` from the checkpoint of ``step`` (ValueError if absent or refused)."""
    ocp = self._ocp
    if step not in self.manager.all_steps():
      raise ValueError(f"{self.directory}: no checkpoint of step {step} (kept: {self.all_steps()})")
    where = self.directory / str(step)
    try:
      meta = self.manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]
    except Exception as e:  # orbax raises many types for a damaged folder
      raise ValueError(f"checkpoint {where} is unreadable ({type(e).__name__}: {e}); "
                       "move it away to resume from an earlier one") from None
    if meta.get("model_config") != self.model_config:
      raise ValueError(f"checkpoint {where} was written by another model config:\n"
                       f"  checkpoint: {meta.get('model_config')}\n  this run:   {self.model_config}\n"
                       "use another --workdir or the matching config")
    target = {"params": state.params, "opt_state": state.opt_state, "step": state.step}
    abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, target)
    try:
      item = self.manager.restore(
          step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract)))["state"]
    except Exception as e:
      raise ValueError(f"checkpoint {where} could not be restored ({type(e).__name__}: {e}); "
                       "it is left untouched") from None
    state = state.replace(step=item["step"], params=item["params"], opt_state=item["opt_state"])
    return state, int(meta["data_position"])

  def close(self):
    self.manager.wait_until_finished()
    self.manager.close()


# --------------------------------------------------------------- main job
VARIANT_FRAMES = {"ours": 3, "ours_s": 1, "usm": 1}
#: USM's training recipes (``config["usm"]["recipe"]``): "ours" trains it with the config's
#: ``train.optim`` and ``train.loss`` (Ours' recipe, the like-for-like default); "published"
#: with USM's own (:data:`nlosjax.models.usm.PUBLISHED_OPTIM`, ``PUBLISHED_LOSS``).
USM_RECIPES = ("ours", "published")

#: Defaults of a config's ``train`` section (the presets override some).
#: ``seeds``: training seeds per variant (``seed``, ``seed + 1``, ...; tables
#: then cover seeds too); ``select_checkpoint``: ``"last"`` or ``"val"`` (the
#: kept checkpoint with the best validation intensity PSNR); ``check_memory``: before
#: any data or parameters exist, compile each variant's train step and refuse when XLA's
#: planned peak exceeds the device's memory (:func:`nlosjax.plan.check_fits`);
#: ``devices``: train data-parallel on the first ``devices`` devices (None: all of them).
TRAIN_DEFAULTS = {
    "steps": 300, "batch_size": 4, "seed": 0, "seeds": 1, "log_every": 10, "checkpoint_every": 50,
    "keep_checkpoints": 2, "eval_batch_size": 8, "variants": ("ours_s", "ours"),
    "data_workers": 1, "optim": {}, "loss": {}, "select_checkpoint": "last",
    "check_memory": False, "devices": None,
}


def with_defaults(config: dict) -> dict:
  """``config`` with :data:`TRAIN_DEFAULTS` filled into its ``train`` section (a new dict)."""
  unknown = set(config.get("train", {})) - set(TRAIN_DEFAULTS)
  if unknown:
    raise ValueError(f"config train section: unknown key(s) {sorted(unknown)}; known: {sorted(TRAIN_DEFAULTS)}")
  return {**config, "train": {**TRAIN_DEFAULTS, **config.get("train", {})}}


def model_config_for(config: dict, setup, variant: str):
  """The model config of ``variant`` for a dataset's Setup.

  ``"ours"`` / ``"ours_s"``: a :class:`~nlosjax.models.network.ModelConfig` from
  ``config["model"]``; ``"usm"``: a :class:`~nlosjax.models.usm.USMConfig`
  from ``config["usm"]["model"]`` (USM's published widths where absent).
  """
  from nlosjax.models.network import ModelConfig
  if variant not in VARIANT_FRAMES:
    raise ValueError(f"variant must be one of {tuple(VARIANT_FRAMES)}, got {variant!r}")
  if variant == "usm":
    from nlosjax.models.usm import USMConfig
    usm = config.get("usm", {})
    return USMConfig(setup=setup, stride=int(config["data"]["input_stride"]),
                     **dict(usm.get("model", {})))
  overrides = dict(config.get("model", {}))
  overrides["frames"] = VARIANT_FRAMES[variant]
  return ModelConfig(setup=setup, stride=int(config["data"]["input_stride"]), **overrides)


def select_frames(measurement: np.ndarray, frames: int) -> np.ndarray:
  """``[B, 3, T, h, w] -> [B, frames, T, h, w]`` centred on the middle frame."""
  mid = measurement.shape[1] // 2
  return measurement[:, mid - frames // 2:mid + frames // 2 + 1]


def make_loader(config: dict, path, split: str, *, batch_size: int, shuffle: bool, seed: int,
                shard: tuple[int, int] = (0, 1)):
  """The config's :class:`~nlosjax.data.dataset.TripletLoader` of ``split`` (the model's under-scan offset checked).

  ``shard = (index, count)``: this process's rows of every global batch.
  """
  from nlosjax.data.dataset import TripletLoader
  data = config["data"]
  opts = data.get("loader", {})
  stride = int(data["input_stride"])
  offset = int(data.get("input_offset", stride // 2))
  if offset != stride // 2:
    raise ValueError(f"config data.input_offset = {offset}, but the model reads scan points "
                     f"stride // 2 + stride * i (offset {stride // 2} for stride {stride})")
  return TripletLoader(path, split=split, batch_size=batch_size, stride=stride, offset=offset,
                       seed=seed, shuffle=shuffle, drop_remainder=shuffle,
                       ends=opts.get("ends", "valid"), target=opts.get("target", "clean"),
                       in_memory=opts.get("in_memory", True), shard=shard)


def ensure_dataset(config: dict, path: pathlib.Path, log: Callable[[str], None] = print) -> None:
  """Generate the config's dataset at ``path``, or add the sequences an existing file lacks.

  An existing file made with the same data configuration but fewer sequences
  (e.g. before the validation split existed) is extended in place, keeping
  every stored sequence (:func:`~nlosjax.data.dataset.extend_dataset`); a file
  made with another configuration is used as it is.
  """
  from nlosjax.data.dataset import DatasetSpec, extend_dataset, write_dataset
  path = pathlib.Path(path)
  spec = DatasetSpec.from_config(config["data"])
  workers = int(config["train"].get("data_workers", 1))
  if path.exists():
    try:
      result = extend_dataset(path, spec, workers=workers)
    except ValueError as e:
      log(f"dataset: using {path} as it is ({e})")
      return
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


def param_fingerprint(params) -> str:
  """A short hash of the parameter tree's paths, shapes and dtypes (not the values).

  Changes when the model code renames or reshapes a layer even though its
  config did not change, so such a checkpoint is refused by name.
  """
  leaves = jax.tree_util.tree_flatten_with_path(params)[0]
  desc = ";".join(f"{jax.tree_util.keystr(path)}:{tuple(x.shape)}:{jnp.dtype(x.dtype).name}"
                  for path, x in leaves)
  return hashlib.sha256(desc.encode()).hexdigest()[:16]


def run_signature(mcfg, params, optim: OptimConfig, weights: losses.LossWeights, batch_size: int,
                  seed: int) -> str:
  """What a checkpoint must have been trained with to be resumed or restored.

  The model config, the parameter tree (:func:`param_fingerprint`), the
  optimiser, the loss weights (:meth:`~nlosjax.losses.LossWeights.to_dict`:
  a weight added later is absent at its default, so older checkpoints still
  resume), the batch size and the seed, as sorted JSON.
  """
  return json.dumps({"model": repr(mcfg), "params": param_fingerprint(params),
                     "optim": dataclasses.asdict(optim), "loss": weights.to_dict(),
                     "batch_size": int(batch_size), "seed": int(seed)}, sort_keys=True)


def train_model(config: dict, data_path, workdir, variant: str, *, folder: str | None = None,
                validate: Callable[[Any, Any], float] | None = None,
                log: Callable[[str], None] = print) -> tuple[Any, TrainState]:
  """Train one variant (``"ours"``, ``"ours_s"`` or ``"usm"``), resuming from ``workdir/<folder>``.

  Args:
    config: the run config (:func:`with_defaults`); the seed is ``config["train"]["seed"]``.
    data_path: the dataset file.
    workdir: the run folder.
    variant: ``"ours"``, ``"ours_s"`` or ``"usm"`` (:data:`VARIANT_FRAMES`).
    folder: sub-folder of this model (default ``variant``).
    validate: ``(model_config, params) -> score`` on the validation split
      (higher is better). With ``config["train"]["select_checkpoint"] ==
      "val"`` every kept checkpoint is scored after training and the best is
      returned; the scores and the choice go to ``<folder>/selection.json``
      (:func:`read_selection`).
  Returns:
    ``(model_config, state)``: after ``config["train"]["steps"]`` steps, or at
    the checkpoint chosen on validation.
  """
  from tqdm import tqdm

  from nlosjax.models.network import format_summary, model_summary
  tr = config["train"]
  steps, batch_size, seed = int(tr["steps"]), int(tr["batch_size"]), int(tr.get("seed", 0))
  vdir = pathlib.Path(workdir) / (folder or variant)
  vdir.mkdir(parents=True, exist_ok=True)
  primary = jax.process_index() == 0
  if not primary:
    log = lambda s: None                                 # noqa: E731 -- one process reports
  loader = make_loader(config, data_path, "train", batch_size=batch_size, shuffle=True, seed=seed,
                       shard=(jax.process_index(), jax.process_count()))
  mcfg = model_config_for(config, loader.setup, variant)
  log(f"[{variant}] " + format_summary(model_summary(mcfg)).replace("\n", f"\n[{variant}] "))
  model = network(mcfg)
  optim, weights = training_recipe(config, variant)
  mesh = mesh_for(config)
  key = jax.random.key(seed)
  init_key, loop_key = jax.random.split(key)
  del key
  shape = (batch_size, mcfg.frames, loader.setup.num_bins) + tuple(loader.input_shape[-2:])
  state = create_train_state(model, shape, make_optimizer(optim, steps), init_key, mesh)
  signature = run_signature(mcfg, state.params, optim, weights, batch_size, seed)
  ckpt = Checkpointer(vdir / "checkpoints", signature, every=int(tr.get("checkpoint_every", 50)),
                      keep=int(tr.get("keep_checkpoints", 2)))
  start = 0
  restored = ckpt.restore_latest(state)
  if restored is not None:
    state, start = restored
    log(f"[{variant}] resumed from step {start} ({ckpt.directory})")
  # One process writes the log (several processes share the workdir); the others write
  # theirs to /dev/null.
  log_path = vdir / "metrics.jsonl" if primary else pathlib.Path(os.devnull)
  if primary:
    kept = [r for r in read_metrics(log_path) if r["step"] <= start]
    log_path.write_text("".join(json.dumps(r) + "\n" for r in kept))
  step_fn = make_train_step(mcfg, weights, mesh)
  log_every = int(tr.get("log_every", 10))
  t_start = time.perf_counter()
  with open(log_path, "a") as f, tqdm(total=steps, initial=start, desc=f"train {variant}",
                                      unit="step", dynamic_ncols=True, mininterval=2.0,
                                      disable=not primary) as bar:
    for step in range(start, steps):
      host = loader.batch(step)
      batch = {k: host[k] for k in BATCH_KEYS}
      batch["measurement"] = select_frames(batch["measurement"], mcfg.frames)
      state, metrics = step_fn(state, shard_batch(batch, mesh), jax.random.fold_in(loop_key, step))
      done = step + 1
      if done % log_every == 0 or done == steps:
        m = {k: float(v) for k, v in to_host(metrics).items()}
        if not all(math.isfinite(v) for v in m.values()):
          raise FloatingPointError(f"[{variant}] non-finite metrics at step {done}: {m}")
        row = {"step": done, "time_s": round(time.perf_counter() - t_start, 3), **m}
        f.write(json.dumps(row) + "\n")
        f.flush()
        bar.set_postfix(loss=f"{m['loss']:.4f}")
      ckpt.save(state, done, force=(done == steps))
      bar.update(1)
  loader.close()
  selection = {"select": str(tr.get("select_checkpoint", "last")), "step": int(state.step),
               "val_psnr": {}}
  if selection["select"] not in ("last", "val"):
    raise ValueError(f'train.select_checkpoint must be "last" or "val", got {selection["select"]!r}')
  if selection["select"] == "val" and validate is not None:
    candidates = {}
    for step in ckpt.all_steps():
      candidate, _ = ckpt.restore(state, step)
      selection["val_psnr"][step] = float(validate(mcfg, to_host(candidate.params)))
      candidates[step] = candidate
    best = max(selection["val_psnr"], key=lambda k: (selection["val_psnr"][k], k))
    state = candidates[best]
    selection["step"] = int(best)
    log(f"[{variant}] checkpoint chosen on validation: step {best} "
        f"({', '.join(f'{k}: {v:.2f} dB' for k, v in selection['val_psnr'].items())})")
  ckpt.close()
  if primary:
    (vdir / "selection.json").write_text(json.dumps(selection, indent=2) + "\n")
  return mcfg, state


def training_recipe(config: dict, variant: str) -> tuple[OptimConfig, losses.LossWeights]:
  """``(optimiser, loss weights)`` a variant trains with.

  The config's ``train.optim`` and ``train.loss``, except for ``"usm"`` with
  ``config["usm"]["recipe"] == "published"`` (:data:`USM_RECIPES`): USM's
  published AdamW (lr 1e-4, weight decay 1e-4, no schedule, no clipping) and loss.
  """
  tr = config["train"]
  if variant == "usm":
    recipe = config.get("usm", {}).get("recipe", "ours")
    if recipe not in USM_RECIPES:
      raise ValueError(f'config usm.recipe must be one of {USM_RECIPES}, got {recipe!r}')
    if recipe == "published":
      from nlosjax.models.usm import PUBLISHED_LOSS, PUBLISHED_OPTIM
      return OptimConfig(**PUBLISHED_OPTIM), losses.LossWeights(**PUBLISHED_LOSS)
  return OptimConfig(**tr.get("optim", {})), losses.LossWeights(**tr.get("loss", {}))


def read_selection(folder) -> dict | None:
  """A model folder's ``selection.json`` (written by :func:`train_model`), or None.

  ``{"select": "last" | "val", "step": chosen step, "val_psnr": {step: dB}}``.
  """
  path = pathlib.Path(folder) / "selection.json"
  if not path.exists():
    return None
  d = json.loads(path.read_text())
  d["val_psnr"] = {int(k): v for k, v in d.get("val_psnr", {}).items()}
  return d
