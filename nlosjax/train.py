"""Training and evaluation of ST-Mamba: state, one pure train step, checkpoints, the main job.

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
* :func:`train_and_evaluate` -- the main job behind ``python -m experiments.train``.

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
import pathlib
import time
from typing import Any, Callable, Iterator

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax.training import train_state
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

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


def make_optimizer(cfg: OptimConfig, total_steps: int) -> optax.GradientTransformation:
  """AdamW with the configured schedule and clipping."""
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
  dummy = jax.ShapeDtypeStruct(tuple(input_shape), jnp.float32)

  def init(k, x):
    params = model.init(k, x)["params"]
    return TrainState.create(apply_fn=model.apply, params=params, tx=tx)

  abstract = jax.eval_shape(init, key, dummy)
  replicated = jax.tree.map(lambda _: NamedSharding(mesh, P()), abstract)
  return jax.jit(init, out_shardings=replicated)(key, jnp.zeros(dummy.shape, dummy.dtype))


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


def make_mesh(devices=None) -> Mesh:
  """A 1D ``Mesh`` named ``"data"`` over ``devices`` (default: every device of every host)."""
  devices = np.asarray(devices if devices is not None else jax.devices())
  return Mesh(devices.reshape(-1), ("data",))


def shard_batch(batch: dict, mesh: Mesh) -> dict:
  """Place a host batch on the mesh, split along axis 0 (the batch must divide evenly)."""
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

  def restore_latest(self, state: TrainState) -> tuple[TrainState, int] | None:
    """``(state, data_position)`` from the latest checkpoint, or None when there is none."""
    step = self.latest_step()
    if step is None:
      return None
    ocp = self._ocp
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


# ------------------------------------------------------------- evaluation
CLASSIC_METHODS = ("fbp", "lct", "fk", "phasor", "rsd")
TABLE_METHODS = CLASSIC_METHODS + ("ours_s", "ours")
METHOD_LABELS = {"fbp": "FBP", "lct": "LCT", "fk": "f-k", "phasor": "Phasor", "rsd": "RSD",
                 "ours_s": "Ours-S", "ours": "Ours"}


def interpolation_matrix(full: int, stride: int) -> np.ndarray:
  """``[full, n]`` linear interpolation from the under-scanned samples to every scan point.

  Sample ``i`` sits at full-grid index ``stride // 2 + stride * i`` (the
  model's :func:`~nlosjax.models.network.underscan`); points outside the
  sampled span take the nearest sample.
  """
  n = len(range(stride // 2, full, stride))
  pos = (np.arange(full) - stride // 2) / stride
  pos = np.clip(pos, 0, n - 1)
  lo = np.minimum(np.floor(pos).astype(int), max(n - 2, 0))
  frac = pos - lo
  m = np.zeros((full, n))
  m[np.arange(full), lo] += 1 - frac
  if n > 1:
    m[np.arange(full), lo + 1] += frac
  return m


def upsample_scan(transient, grid: tuple[int, int], stride: int) -> jax.Array:
  """``[..., T, h, w] -> [..., T, H, W]`` bilinear interpolation onto the full scan grid (paper protocol)."""
  my = jnp.asarray(interpolation_matrix(grid[0], stride), jnp.float32)
  mx = jnp.asarray(interpolation_matrix(grid[1], stride), jnp.float32)
  if transient.shape[-2:] != (my.shape[1], mx.shape[1]):
    raise ValueError(f"under-scanned grid {transient.shape[-2:]} does not match grid {grid} "
                     f"at stride {stride} ({my.shape[1]}, {mx.shape[1]})")
  return jnp.einsum("Hh,...thw,Ww->...tHW", my, jnp.asarray(transient, jnp.float32), mx)


def classic_options(method: str, setup) -> dict:
  """Options of a classic baseline on ``setup``: the defaults, with a resolved phasor wavelet.

  Phasor and RSD get ``sampling_coeff`` from
  :func:`~nlosjax.physics.wavelet.resolved_sampling_coeff` where their default
  virtual wavelength (4 scan spacings) is under 3 time bins (the ``real``
  preset); elsewhere (``cpu``, ``paper``, the measured scans) ``{}``.
  """
  from nlosjax.physics.wavelet import resolved_sampling_coeff
  if method not in ("phasor", "rsd"):
    return {}
  coeff = resolved_sampling_coeff(setup)
  return {} if coeff <= 2.0 else {"sampling_coeff": coeff}


def classic_images(measurement, setup, stride: int, method: str) -> tuple[np.ndarray, np.ndarray]:
  """Intensity and depth of a classic method on under-scanned input.

  Args:
    measurement: ``[N, T, h, w]`` counts of the frames to reconstruct.
    setup: the full-grid Setup.
    stride: the under-scan stride (the input is interpolated to the full grid).
    method: one of :data:`CLASSIC_METHODS` (options: :func:`classic_options`).
  Returns:
    ``(intensity [N, H, W] in [0, 1], depth [N, H, W] metres)`` as NumPy.
  """
  from nlosjax.physics import intensity_depth, reconstruct
  full = upsample_scan(measurement, setup.grid, stride)
  vol = reconstruct(full, setup, method, **classic_options(method, setup))
  if method == "fk":
    vol = jnp.sqrt(vol)                      # f-k returns albedo squared
  inten, depth = intensity_depth(vol, setup)
  return np.asarray(inten), np.asarray(depth)


def image_metrics(intensity, depth, gt_intensity, gt_depth) -> dict:
  """Per-frame ``psnr``, ``ssim`` (intensity, data range 1) and ``rmse``, ``mad`` (depth, metres)."""
  from nlosjax import metrics
  return {"psnr": np.asarray(metrics.psnr(intensity, gt_intensity)),
          "ssim": np.asarray(metrics.ssim(intensity, gt_intensity)),
          "rmse": np.asarray(metrics.rmse(depth, gt_depth)),
          "mad": np.asarray(metrics.mad(depth, gt_depth))}


def summarise(per_frame: dict) -> dict:
  """``metric -> [mean, std]`` over frames."""
  return {k: [float(np.mean(v)), float(np.std(v))] for k, v in per_frame.items()}


def format_table(table: dict, caption: str = "") -> str:
  """Markdown of ``method -> metric -> [mean, std]`` in the paper's Table 1 layout."""
  lines = ([caption, ""] if caption else []) + [
      "| method | intensity PSNR (dB) ↑ | intensity SSIM ↑ | depth RMSE (m) ↓ | depth MAD (m) ↓ |",
      "|---|---|---|---|---|"]
  for m in TABLE_METHODS:
    if m not in table:
      continue
    r = table[m]
    lines.append(f"| {METHOD_LABELS[m]} | {r['psnr'][0]:.2f} ± {r['psnr'][1]:.2f} | "
                 f"{r['ssim'][0]:.3f} ± {r['ssim'][1]:.3f} | {r['rmse'][0]:.4f} ± {r['rmse'][1]:.4f} | "
                 f"{r['mad'][0]:.4f} ± {r['mad'][1]:.4f} |")
  return "\n".join(lines) + "\n"


# --------------------------------------------------------------- main job
VARIANT_FRAMES = {"ours": 3, "ours_s": 1}

#: Defaults of a config's ``train`` section (the presets override some).
TRAIN_DEFAULTS = {
    "steps": 300, "batch_size": 4, "seed": 0, "log_every": 10, "checkpoint_every": 50,
    "keep_checkpoints": 2, "eval_batch_size": 8, "variants": ("ours_s", "ours"),
    "data_workers": 1, "optim": {}, "loss": {},
}


def with_defaults(config: dict) -> dict:
  """``config`` with :data:`TRAIN_DEFAULTS` filled into its ``train`` section (a new dict)."""
  unknown = set(config.get("train", {})) - set(TRAIN_DEFAULTS)
  if unknown:
    raise ValueError(f"config train section: unknown key(s) {sorted(unknown)}; known: {sorted(TRAIN_DEFAULTS)}")
  return {**config, "train": {**TRAIN_DEFAULTS, **config.get("train", {})}}


def model_config_for(config: dict, setup, variant: str):
  """The :class:`~nlosjax.models.network.ModelConfig` of ``variant`` for a dataset's Setup."""
  from nlosjax.models.network import ModelConfig
  if variant not in VARIANT_FRAMES:
    raise ValueError(f"variant must be one of {tuple(VARIANT_FRAMES)}, got {variant!r}")
  overrides = dict(config.get("model", {}))
  overrides["frames"] = VARIANT_FRAMES[variant]
  return ModelConfig(setup=setup, stride=int(config["data"]["input_stride"]), **overrides)


def _select_frames(measurement: np.ndarray, frames: int) -> np.ndarray:
  """``[B, 3, T, h, w] -> [B, frames, T, h, w]`` centred on the middle frame."""
  mid = measurement.shape[1] // 2
  return measurement[:, mid - frames // 2:mid + frames // 2 + 1]


def _loader(config: dict, path, split: str, *, batch_size: int, shuffle: bool, seed: int):
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
                       in_memory=opts.get("in_memory", True))


def ensure_dataset(config: dict, path: pathlib.Path, log: Callable[[str], None] = print) -> None:
  """Generate the config's dataset at ``path`` unless a file is already there."""
  from nlosjax.data.dataset import DatasetSpec, write_dataset
  if path.exists():
    log(f"dataset: using {path}")
    return
  log(f"dataset: generating {path} ...")
  t0 = time.perf_counter()
  spec = DatasetSpec.from_config(config["data"])
  write_dataset(path, spec, workers=int(config["train"].get("data_workers", 1)))
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
  optimiser, the loss weights, the batch size and the seed, as sorted JSON.
  """
  return json.dumps({"model": repr(mcfg), "params": param_fingerprint(params),
                     "optim": dataclasses.asdict(optim), "loss": dataclasses.asdict(weights),
                     "batch_size": int(batch_size), "seed": int(seed)}, sort_keys=True)


def train_model(config: dict, data_path, workdir, variant: str, *,
                log: Callable[[str], None] = print) -> tuple[Any, TrainState]:
  """Train one variant (``"ours"`` or ``"ours_s"``), resuming from ``workdir/<variant>``.

  Returns ``(model_config, state)`` after ``config["train"]["steps"]`` steps.
  """
  from nlosjax.models.network import STMambaNet, format_summary, model_summary
  from tqdm import tqdm
  tr = config["train"]
  steps, batch_size, seed = int(tr["steps"]), int(tr["batch_size"]), int(tr.get("seed", 0))
  vdir = pathlib.Path(workdir) / variant
  vdir.mkdir(parents=True, exist_ok=True)
  loader = _loader(config, data_path, "train", batch_size=batch_size, shuffle=True, seed=seed)
  mcfg = model_config_for(config, loader.setup, variant)
  log(f"[{variant}] " + format_summary(model_summary(mcfg)).replace("\n", f"\n[{variant}] "))
  model = STMambaNet(mcfg)
  optim = OptimConfig(**tr.get("optim", {}))
  weights = losses.LossWeights(**tr.get("loss", {}))
  mesh = make_mesh()
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
  log_path = vdir / "metrics.jsonl"
  kept = [r for r in read_metrics(log_path) if r["step"] <= start]
  log_path.write_text("".join(json.dumps(r) + "\n" for r in kept))
  step_fn = make_train_step(mcfg, weights, mesh)
  log_every = int(tr.get("log_every", 10))
  t_start = time.perf_counter()
  with open(log_path, "a") as f, tqdm(total=steps, initial=start, desc=f"train {variant}",
                                      unit="step", dynamic_ncols=True, mininterval=2.0) as bar:
    for step in range(start, steps):
      host = loader.batch(step)
      batch = {k: host[k] for k in BATCH_KEYS}
      batch["measurement"] = _select_frames(batch["measurement"], mcfg.frames)
      state, metrics = step_fn(state, shard_batch(batch, mesh), jax.random.fold_in(loop_key, step))
      done = step + 1
      if done % log_every == 0 or done == steps:
        m = {k: float(v) for k, v in jax.device_get(metrics).items()}
        if not all(math.isfinite(v) for v in m.values()):
          raise FloatingPointError(f"[{variant}] non-finite metrics at step {done}: {m}")
        row = {"step": done, "time_s": round(time.perf_counter() - t_start, 3), **m}
        f.write(json.dumps(row) + "\n")
        f.flush()
        bar.set_postfix(loss=f"{m['loss']:.4f}")
      ckpt.save(state, done, force=(done == steps))
      bar.update(1)
  ckpt.close()
  loader.close()
  return mcfg, state


def evaluate_model(mcfg, params, loader) -> dict:
  """Per-frame images of a trained model on a loader's examples (in order).

  Returns ``{"intensity": [N, H, W], "depth": [N, H, W]}`` NumPy.
  """
  from nlosjax.models.network import STMambaNet
  model = STMambaNet(mcfg)
  apply = jax.jit(lambda p, x: model.apply({"params": p}, x))
  inten, depth = [], []
  for step in range(len(loader)):
    b = loader.batch(step)
    x = _select_frames(b["measurement"], mcfg.frames)
    out = apply(params, jnp.asarray(x))
    inten.append(np.asarray(out["intensity"]))
    depth.append(np.asarray(out["depth"]))
  return {"intensity": np.concatenate(inten), "depth": np.concatenate(depth)}


def evaluate(config: dict, data_path, trained: dict, *, split: str = "test",
             methods: tuple[str, ...] = CLASSIC_METHODS,
             log: Callable[[str], None] = print) -> tuple[dict, dict]:
  """Table 1 on ``split``: classic methods (under-scanned input interpolated) and trained models.

  Args:
    config: the run config.
    data_path: an HDF5 file in the documented layout.
    trained: ``variant -> (model_config, params)``.
    methods: the classic methods to include.
  Returns:
    ``(table, images)``: ``method -> metric -> [mean, std]`` and
    ``method -> {"intensity", "depth"}`` arrays ``[N, H, W]`` (plus ``"gt"``).
  """
  from tqdm import tqdm
  batch_size = int(config["train"].get("eval_batch_size", config["train"]["batch_size"]))
  loader = _loader(config, data_path, split, batch_size=batch_size, shuffle=False, seed=0)
  gt_i, gt_d, mid = [], [], []
  for step in range(len(loader)):
    b = loader.batch(step)
    gt_i.append(b["intensity"])
    gt_d.append(b["depth"])
    mid.append(b["measurement"][:, 1])
  gt = {"intensity": np.concatenate(gt_i), "depth": np.concatenate(gt_d)}
  mid = np.concatenate(mid)
  images = {"gt": gt}
  table = {}
  for method in tqdm(methods, desc="classic methods", unit="method", disable=not methods):
    out_i, out_d = [], []
    for s in range(0, len(mid), batch_size):
      i, d = classic_images(mid[s:s + batch_size], loader.setup, loader.stride, method)
      out_i.append(i)
      out_d.append(d)
    images[method] = {"intensity": np.concatenate(out_i), "depth": np.concatenate(out_d)}
  for variant, (mcfg, params) in trained.items():
    images[variant] = evaluate_model(mcfg, params, loader)
  for method, im in images.items():
    if method != "gt":
      table[method] = summarise(image_metrics(im["intensity"], im["depth"], gt["intensity"],
                                              gt["depth"]))
  loader.close()
  log(format_table(table, f"{split} split of {data_path}: {len(mid)} frames"))
  return table, images


# ---------------------------------------------------------------- figures
def plot_comparison(images: dict, path, *, frames: int = 3, max_depth: float | None = None) -> None:
  """Intensity (top) and depth (bottom) rows per test frame: ground truth, then each method."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  methods = ["gt"] + [m for m in TABLE_METHODS if m in images]
  n = min(frames, len(images["gt"]["intensity"]))
  idx = np.linspace(0, len(images["gt"]["intensity"]) - 1, n).round().astype(int)
  dmax = max_depth or float(np.max(images["gt"]["depth"])) or 1.0
  fig, axes = plt.subplots(2 * n, len(methods), figsize=(1.6 * len(methods), 3.2 * n), squeeze=False)
  for r, k in enumerate(idx):
    for c, m in enumerate(methods):
      for j, (key, kw) in enumerate((("intensity", dict(cmap="gray", vmin=0, vmax=1)),
                                     ("depth", dict(cmap="viridis", vmin=0, vmax=dmax)))):
        ax = axes[2 * r + j, c]
        ax.imshow(images[m][key][k], **kw)
        ax.set_xticks([])
        ax.set_yticks([])
        if r == 0 and j == 0:
          ax.set_title("GT" if m == "gt" else METHOD_LABELS[m], fontsize=9)
        if c == 0:
          ax.set_ylabel(f"frame {k}\n{key}", fontsize=8)
  fig.suptitle(f"intensity (gray, [0, 1]) and depth (viridis, 0-{dmax:.2f} m)", fontsize=9)
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)


def plot_training_curves(logs: dict, path) -> None:
  """Total loss and each term against step, one line per variant."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  keys = ["loss", "pf", "t", "int", "dep"]
  fig, axes = plt.subplots(1, len(keys), figsize=(3.2 * len(keys), 2.8))
  for ax, k in zip(axes, keys):
    for variant, rows in logs.items():
      rows = [r for r in rows if k in r]
      if rows:
        ax.plot([r["step"] for r in rows], [r[k] for r in rows], label=METHOD_LABELS[variant])
    ax.set_title(k)
    ax.set_xlabel("step")
    ax.set_yscale("log")
  axes[0].legend()
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)


def write_results(table: dict, images: dict, out_dir, *, caption: str, logs: dict | None = None) -> None:
  """``table.md``, ``table.json``, ``comparison.png`` (and ``training_curves.png``) in ``out_dir``."""
  out = pathlib.Path(out_dir)
  out.mkdir(parents=True, exist_ok=True)
  (out / "table.json").write_text(json.dumps(table, indent=2) + "\n")
  (out / "table.md").write_text(format_table(table, caption))
  plot_comparison(images, out / "comparison.png")
  if logs:
    plot_training_curves(logs, out / "training_curves.png")


def train_and_evaluate(config: dict, workdir) -> dict:
  """The main job: make the dataset if absent, train Ours-S and Ours, evaluate, write results.

  Writes into ``workdir``: ``<variant>/checkpoints``, ``<variant>/metrics.jsonl``,
  ``config.json``, and ``results/{table.md, table.json, comparison.png,
  training_curves.png}``. Resumes from the checkpoints of an earlier,
  interrupted run with the same config.

  Returns:
    the table ``method -> metric -> [mean, std]``.
  """
  config = with_defaults(config)
  workdir = pathlib.Path(workdir)
  workdir.mkdir(parents=True, exist_ok=True)
  (workdir / "config.json").write_text(json.dumps(config, indent=2, default=str) + "\n")
  t0 = time.perf_counter()
  data_path = pathlib.Path(config["data"]["path"])
  ensure_dataset(config, data_path)
  trained, logs = {}, {}
  for variant in config["train"].get("variants", ("ours_s", "ours")):
    mcfg, state = train_model(config, data_path, workdir, variant)
    trained[variant] = (mcfg, state.params)
    logs[variant] = read_metrics(workdir / variant / "metrics.jsonl")
  table, images = evaluate(config, data_path, trained)
  caption = (f"Test split of `{data_path}` ({len(images['gt']['intensity'])} frames); "
             f"{config['train']['steps']} steps of batch {config['train']['batch_size']}; "
             f"{jax.devices()[0].platform}, {jax.device_count()} device(s); "
             f"main job wall time {time.perf_counter() - t0:.0f} s.")
  write_results(table, images, workdir / "results", caption=caption, logs=logs)
  print(f"results written to {workdir / 'results'} ({time.perf_counter() - t0:.0f} s in all)")
  return table
