"""A second training stage: the synthetic loss plus a term that aligns features of synthetic and measured inputs.

Starting from a trained network, :func:`align` trains every parameter on

    L = L_synthetic(batch) + lam * MMD^2(f(batch), f(measured))

where ``f`` is the output of one layer (``layer``, default the first ST-Mamba
block: per frame, per time step and scan point a ``C``-vector of features)
at ``samples`` positions drawn at random from each side and standardised by
the synthetic side's mean and spread, and ``MMD^2`` the unbiased Gaussian-kernel
discrepancy (:func:`nlosjax.losses.mmd2`). ``measured`` are unlabelled
under-scanned inputs ``[M, F, T, h, w]`` (static scans: one frame repeated);
each step reads ``measured_batch`` of them. Steps, learning rate and ``lam``
are fixed beforehand: nothing is chosen on the measured inputs' scores, and
a caller that scores a scan must leave that scan's inputs out of
``measured`` (``experiments.studies.align``).

``lam`` may be set from the training side alone: :func:`term_gradient_norms` measures
each term's gradient norm at the starting parameters on synthetic training batches and
the (training) measured inputs, and :func:`balanced_lam` the ``lam`` at which the MMD
term pulls as hard as the synthetic loss (the median norms' ratio times ``share``).
"""

from __future__ import annotations

import functools
import json
import pathlib
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax

from nlosjax import losses
from nlosjax.train.step import make_targets
from nlosjax.variants import OURS, OURS_S

__all__ = ["DEFAULT_LAYER", "layer_features", "all_layer_features", "layer_separation", "chosen_layer",
           "standardised_mmd2", "align_loss", "align", "term_gradient_norms", "balanced_lam"]

#: The layer whose output is aligned.
DEFAULT_LAYER = "st_mamba0"


def _sublayer_outputs(model, params, frames, keep) -> tuple:
  """``(outputs, {name: output})`` of the model and of its direct sub-modules ``keep(name)`` selects."""
  out, state = model.apply({"params": params}, frames, mutable=["intermediates"],
                           capture_intermediates=lambda mdl, method: method == "__call__"
                           and len(mdl.scope.path) == 1 and keep(mdl.name))
  found = {}
  for name, value in state.get("intermediates", {}).items():
    feat = value.get("__call__", (None,))[0] if isinstance(value, dict) else None
    if isinstance(feat, jax.Array):
      found[name] = feat
  return out, found


def _as_rows(feat: jax.Array) -> jax.Array:
  """``[..., C] -> [N, C]`` float32: one row per position."""
  return jnp.reshape(feat.astype(jnp.float32), (-1, feat.shape[-1]))


def layer_features(model, params, frames, layer: str = DEFAULT_LAYER):
  """``(outputs, features [N, C])``: the model's outputs and ``layer``'s output, one row per position."""
  out, found = _sublayer_outputs(model, params, frames, lambda name: name == layer)
  if layer not in found:
    _, every = _sublayer_outputs(model, params, frames, lambda name: True)
    raise ValueError(f"layer {layer!r} is not a module of this network; it has {sorted(every)}")
  return out, _as_rows(found[layer])


def all_layer_features(model, params, frames) -> dict[str, np.ndarray]:
  """``layer -> features [N, C]`` of every direct sub-module whose output is ``[B, T, h, w, C]``.

  The layers whose outputs keep a feature vector per frame, time step and scan point (the
  network's extraction, ST-Mamba and cross blocks), in the order the network runs them.
  """
  return {k: np.asarray(v) for k, v in _layer_outputs(model, params, frames).items()}


def _layer_outputs(model, params, frames) -> dict:
  """:func:`all_layer_features` as device arrays (jittable)."""
  _, found = _sublayer_outputs(model, params, frames, lambda name: True)
  return {name: _as_rows(feat) for name, feat in found.items() if feat.ndim == 5}


def standardised_mmd2(reference, *others):
  """MMD² (:func:`nlosjax.losses.mmd2`) of ``reference [n, C]`` to each of ``others [m, C]``.

  Every sample is standardised by ``reference``'s mean and spread per channel (``+ 1e-6``),
  through which no gradient flows, so the term compares shapes, not scales. Returns a tuple.
  """
  mu = jax.lax.stop_gradient(jnp.mean(reference, 0))
  sd = jax.lax.stop_gradient(jnp.std(reference, 0)) + 1e-6
  ref = (reference - mu) / sd
  return tuple(losses.mmd2(ref, (b - mu) / sd) for b in others)


def layer_separation(model_config, params, synthetic: np.ndarray, measured: np.ndarray, *, samples: int = 512,
                     draws: int = 16, batch_size: int = 4, seed: int = 0) -> dict[str, dict]:
  """How far each layer's features of ``measured`` inputs stand from those of ``synthetic`` ones.

  For every layer of :func:`all_layer_features`, ``draws`` times: ``samples`` feature vectors drawn
  from the synthetic inputs twice (``a``, ``a'``) and from the measured ones once (``b``), all
  standardised by ``a``'s mean and spread (as :func:`align_loss`); ``mmd`` is MMD²(a, b) and
  ``null`` MMD²(a, a'), what the estimate gives between two samples of one distribution. ``z``
  = (mean mmd − mean null) / spread of null: how many noise widths the measured features stand
  off. A layer with a large ``z`` is one where the alignment term has something to align.

  Args:
    model_config, params: the network (:class:`~nlosjax.models.ModelConfig` and parameters).
    synthetic: ``[S, F, T, h, w]`` inputs of the training distribution; measured: ``[M, F, T, h, w]``
      unlabelled measured inputs at the same Setup (never a scan that is then scored).
    samples, draws: per estimate, and estimates per layer.
  Returns:
    ``layer -> {"channels", "mmd", "mmd_sd", "null", "null_sd", "z"}`` (floats), in network order.
  """
  if not (samples >= 2 and draws >= 2 and batch_size >= 1):
    raise ValueError(f"samples >= 2, draws >= 2 and batch_size >= 1 are needed, got {samples}, {draws}, {batch_size}")
  from nlosjax.physics import operator_args
  apply = operator_args.bind(functools.partial(_layer_outputs, model_config.module()),
                             model_config.physics_operators())

  def features(x):
    parts = [apply(params, jnp.asarray(x[i:i + batch_size])) for i in range(0, len(x), batch_size)]
    return {k: np.concatenate([np.asarray(p[k]) for p in parts]) for k in parts[0]}

  syn, meas = features(np.asarray(synthetic, np.float32)), features(np.asarray(measured, np.float32))
  rng = np.random.default_rng(seed)
  mmd = jax.jit(standardised_mmd2)
  out = {}
  for name, fs in syn.items():
    fm = meas[name]
    between, null = [], []
    for _ in range(draws):
      a, a2 = fs[rng.integers(0, len(fs), samples)], fs[rng.integers(0, len(fs), samples)]
      b = fm[rng.integers(0, len(fm), samples)]
      to_b, to_a2 = mmd(a, b, a2)
      between.append(float(to_b))
      null.append(float(to_a2))
    spread = float(np.std(null, ddof=1))
    out[name] = {"channels": int(fs.shape[1]), "mmd": float(np.mean(between)),
                 "mmd_sd": float(np.std(between, ddof=1)), "null": float(np.mean(null)), "null_sd": spread,
                 "z": (float(np.mean(between)) - float(np.mean(null))) / max(spread, 1e-12)}
  return out


def chosen_layer(separation: dict[str, dict]) -> str:
  """The layer of :func:`layer_separation` whose measured features stand furthest off (largest ``z``)."""
  if not separation:
    raise ValueError("no layer to choose from")
  return max(separation, key=lambda name: separation[name]["z"])


def _sample(x, key, n):
  return x[jax.random.randint(key, (n,), 0, x.shape[0])]


def align_loss(params, batch, measured, key, *, model, weights, wavelet, time_window, lam: float,
               samples: int, layer: str = DEFAULT_LAYER):
  """``(total, terms)``: the synthetic loss of ``batch`` plus ``lam`` times the features' MMD² to ``measured``.

  ``batch``: as :func:`nlosjax.train.train_step`'s; ``measured``: ``[M, F, T, h, w]`` counts.
  """
  out, f_syn = layer_features(model, params, batch["measurement"], layer)
  _, f_meas = layer_features(model, params, measured, layer)
  loss, terms = losses.total_loss(out, make_targets(batch, time_window), weights, wavelet)
  k1, k2 = jax.random.split(key)
  (mmd,) = standardised_mmd2(_sample(f_syn, k1, samples), _sample(f_meas, k2, samples))
  total = loss + lam * mmd
  return total, {**terms, "mmd": mmd, "synthetic": loss, "loss": total}


def _checked_measured(measured, model_config) -> np.ndarray:
  measured = np.asarray(measured, np.float32)
  if measured.ndim != 5 or measured.shape[1:] != tuple(model_config.input_shape(1))[1:]:
    raise ValueError(f"measured must be [M, F, T, h, w] = [M, *{model_config.input_shape(1)[1:]}], "
                     f"got {measured.shape}")
  return measured


def _loss_fn(config, model_config, *, lam: float, samples: int, layer: str):
  """:func:`align_loss` bound to the run's model, loss weights and wavelet."""
  from nlosjax.physics import illumination_wavelet
  from nlosjax.train.loop import training_recipe
  _, weights = training_recipe(config, OURS if model_config.frames > 1 else OURS_S)
  wavelet = (illumination_wavelet(model_config.setup, cycles=model_config.wavelet_cycles,
                                  sampling_coeff=model_config.wavelet_sampling)
             if weights.phasor_field else None)
  return functools.partial(align_loss, model=model_config.module(), weights=weights, wavelet=wavelet,
                           time_window=model_config.time_window, lam=lam, samples=samples, layer=layer)


def _device_batch(host: dict, model_config) -> dict:
  """A loader batch on the device, its measurement cut to the network's frames."""
  from nlosjax.train.loop import select_frames
  batch = {name: jnp.asarray(host[name]) for name in ("measurement", "transient", "intensity", "depth")}
  batch["measurement"] = jnp.asarray(select_frames(host["measurement"], model_config.frames))
  return batch


def term_gradient_norms(config, data_path, model_config, params, measured: np.ndarray, *,
                        batches: int = 8, measured_batch: int = 4, samples: int = 512,
                        layer: str = DEFAULT_LAYER, seed: int = 0) -> dict:
  """Each term's global gradient norm at ``params``, on ``batches`` synthetic training batches.

  As :func:`align`'s first steps draw them (same loader order, measured draws and sample
  keys for ``seed``), but nothing is trained: the norms of the gradients of the synthetic
  loss and of the MMD² term (:func:`align_loss`'s ``"synthetic"`` and ``"mmd"``) with
  respect to every parameter, and the MMD² itself. ``measured``: ``[M, F, T, h, w]``, the
  inputs the stage will train on (never a scan that is then scored).

  Returns ``{"synthetic": [batches], "mmd": [batches], "mmd_value": [batches]}`` (floats).
  """
  from nlosjax.physics import operator_args
  from nlosjax.train.loop import make_loader
  measured = _checked_measured(measured, model_config)
  if not (isinstance(batches, int) and batches >= 1 and measured_batch >= 1 and samples >= 2):
    raise ValueError("batches >= 1, measured_batch >= 1 and samples >= 2 are needed")
  loss_fn = _loss_fn(config, model_config, lam=1.0, samples=int(samples), layer=layer)

  def norms(p, batch, meas, key):
    # One forward, two pullbacks: the cotangents (1, 0) and (0, 1) pick each term's gradient.
    terms, pullback = jax.vjp(lambda q: _terms(loss_fn(q, batch, meas, key)[1]), p)
    one, zero = jnp.ones_like(terms[0]), jnp.zeros_like(terms[0])
    (g_syn,), (g_mmd,) = pullback((one, zero)), pullback((zero, one))
    return optax.global_norm(g_syn), optax.global_norm(g_mmd), terms[1]

  run = operator_args.bind(norms, model_config.physics_operators())
  loader = make_loader(config, data_path, "train", batch_size=config.train.batch_size,
                       shuffle=True, seed=seed)
  rng = np.random.default_rng(seed)
  key = jax.random.key(seed)
  p = jax.tree_util.tree_map(jnp.asarray, params)
  out = {"synthetic": [], "mmd": [], "mmd_value": []}
  try:
    for k in range(batches):
      batch = _device_batch(loader.batch(k), model_config)
      meas = jnp.asarray(measured[rng.choice(measured.shape[0], measured_batch)])
      for name, v in zip(out, run(p, batch, meas, jax.random.fold_in(key, k))):
        out[name].append(float(v))
  finally:
    loader.close()
  return out


def _terms(parts: dict) -> tuple:
  """``(synthetic, mmd)`` from :func:`align_loss`'s parts, as one output for :func:`jax.vjp`."""
  return parts["synthetic"], parts["mmd"]


def balanced_lam(norms: dict, share: float = 1.0) -> float:
  """``share`` times the median synthetic gradient norm over the median MMD² one (:func:`term_gradient_norms`).

  At that ``lam`` the MMD term's gradient is, in the median, ``share`` times as large as
  the synthetic loss's. Raises ``ValueError`` when the MMD gradient is zero or not finite.
  """
  syn, mmd = float(np.median(norms["synthetic"])), float(np.median(norms["mmd"]))
  if not (np.isfinite(syn) and np.isfinite(mmd) and mmd > 0 and share > 0):
    raise ValueError(f"no balanced lam: median gradient norms synthetic {syn}, mmd {mmd}, share {share}")
  return share * syn / mmd


def align(config, data_path, model_config, params, measured: np.ndarray, workdir, *,
          steps: int = 100, learning_rate: float = 1e-4, lam: float = 1.0, measured_batch: int = 4,
          samples: int = 512, layer: str = DEFAULT_LAYER, validate: Callable | None = None,
          every: int = 25, seed: int = 0, extra: dict | None = None,
          log: Callable[[str], None] = print) -> tuple[dict, dict]:
  """Run the second stage (module docstring) for ``steps`` steps; returns ``(params, record)``.

  Args:
    config: the run config of the synthetic data and loss (a :class:`~nlosjax.train.RunConfig`).
    data_path: its dataset file (the ``train`` split is read).
    model_config, params: the trained network (its config at the data's Setup).
    measured: ``[M, F, T, h, w]`` unlabelled measured inputs at the same Setup, ``M >= 1``.
    workdir: where ``align.json`` (the record) and ``params.npz`` (the result, keyed as
      :func:`nlosjax.pretrained.flatten_params`) are written.
    steps, learning_rate, lam, measured_batch, samples, layer: the stage (module docstring).
    validate: optional ``(model_config, params) -> validation PSNR``, scored every ``every`` steps.
    seed: the synthetic batches' order and the samples' draws.
    extra: more entries for the record (e.g. how ``lam`` was set).
  Returns:
    ``(params, record)``; ``record``: the settings, the loss terms every ``every`` steps, the
    validation scores, the wall time.
  """
  from nlosjax.physics import operator_args
  from nlosjax.pretrained import flatten_params
  from nlosjax.train.loop import make_loader
  measured = _checked_measured(measured, model_config)
  if not (isinstance(steps, int) and steps >= 1 and lam >= 0 and measured_batch >= 1 and samples >= 2):
    raise ValueError("steps >= 1, lam >= 0, measured_batch >= 1 and samples >= 2 are needed")
  t0 = time.perf_counter()
  workdir = pathlib.Path(workdir)
  workdir.mkdir(parents=True, exist_ok=True)
  loss_fn = _loss_fn(config, model_config, lam=float(lam), samples=int(samples), layer=layer)
  tx = optax.adam(learning_rate)

  def step(p, opt_state, batch, meas, key):
    (_, terms), grads = jax.value_and_grad(loss_fn, has_aux=True)(p, batch, meas, key)
    updates, opt_state = tx.update(grads, opt_state, p)
    return optax.apply_updates(p, updates), opt_state, terms

  run = operator_args.bind(step, model_config.physics_operators())
  batch_size = config.train.batch_size
  loader = make_loader(config, data_path, "train", batch_size=batch_size, shuffle=True, seed=seed)
  rng = np.random.default_rng(seed)
  key = jax.random.key(seed)
  p = jax.tree_util.tree_map(jnp.asarray, params)
  opt_state = tx.init(p)
  curve = []
  record = {"steps": steps, "learning_rate": learning_rate, "lam": lam, "measured_batch": measured_batch,
            "samples": samples, "layer": layer, "measured_inputs": int(measured.shape[0]), "seed": seed,
            "curve": curve, **(extra or {})}
  if validate is not None:
    curve.append({"step": 0, "val_psnr": float(validate(model_config, jax.tree_util.tree_map(np.asarray, p)))})
  try:
    for k in range(steps):
      batch = _device_batch(loader.batch(k), model_config)
      meas = jnp.asarray(measured[rng.choice(measured.shape[0], measured_batch)])
      p, opt_state, terms = run(p, opt_state, batch, meas, jax.random.fold_in(key, k))
      done = k + 1
      if done % every == 0 or done == steps:
        row = {"step": done, **{name: float(v) for name, v in terms.items() if name in ("loss", "synthetic", "mmd")}}
        if validate is not None:
          row["val_psnr"] = float(validate(model_config, jax.tree_util.tree_map(np.asarray, p)))
        curve.append(row)
        log(f"[align] step {done}: " + ", ".join(f"{n} {v:.4f}" for n, v in row.items() if n != "step"))
  finally:
    loader.close()
  params = jax.tree_util.tree_map(np.asarray, p)
  record["seconds"] = round(time.perf_counter() - t0, 1)
  np.savez(workdir / "params.npz", **flatten_params(params))
  (workdir / "align.json").write_text(json.dumps(record, indent=1) + "\n")
  return params, record
