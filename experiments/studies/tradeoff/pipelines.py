"""The jittable pipelines ``input -> (intensity, depth)`` that are timed: a classic method on
the interpolated scan (:func:`classic_pipeline`) and a network (:func:`learned_pipeline`).
"""

from __future__ import annotations

from typing import Callable

from experiments.studies.tradeoff.configs import CLASSIC


def classic_pipeline(method: str, setup, stride: int, *, volume: bool = False) -> Callable:
  """``x [B, T, h, w] -> {"intensity", "depth" [B, H, W] (, "volume" [B, Z, H, W])}``.

  The evaluation protocol of :func:`nlosjax.evaluation.baselines.classic_images`: the
  under-scanned counts interpolated bilinearly onto ``setup``'s grid, the
  method's volume (``sqrt`` of f-k's albedo squared), then
  :func:`nlosjax.physics.intensity_depth`. Jittable.
  """
  import jax
  import jax.numpy as jnp

  from nlosjax.evaluation.baselines import TABLE_VARIANT, upsample_scan
  from nlosjax.physics import intensity_depth, reconstruct
  if method not in CLASSIC:
    raise ValueError(f"method must be one of {CLASSIC}, got {method!r}")

  def fn(x):
    # The methods cache their operators per Setup; built under this trace they would be
    # cached as tracers and leak into later calls. Concrete values are computed eagerly here.
    with jax.ensure_compile_time_eval():
      vol = reconstruct(upsample_scan(x, setup.grid, stride), setup, method,
                        **({"variant": TABLE_VARIANT[method]} if method in TABLE_VARIANT else {}))
    if method == "fk":
      vol = jnp.sqrt(vol)
    inten, depth = intensity_depth(vol, setup)
    out = {"intensity": inten, "depth": depth}
    if volume:
      out["volume"] = vol
    return out

  return fn


def csa_pipeline(setup, stride: int, *, tau_rel: float, falloff: str) -> Callable:
  """``x [B, T, h, w] -> {"intensity", "depth" [B, H, W]}`` of CSA on the sparse scan.

  The under-scanned counts are placed at their scan points of ``setup``'s grid
  (:func:`nlosjax.physics.methods.csa.sparse_on_grid`; zeros elsewhere, never read: the
  sampling mask :func:`~nlosjax.physics.methods.csa.interval_mask`), then
  :func:`nlosjax.physics.methods.csa.csa` (at most 200 FISTA steps, tol 1e-4) and
  :func:`nlosjax.physics.intensity_depth`. Jittable.
  """
  import jax

  from nlosjax.physics import intensity_depth
  from nlosjax.physics.methods import csa
  H, W = setup.grid
  mask = csa.interval_mask(H, W, stride)

  def fn(x):
    full = csa.sparse_on_grid(x, (H, W), stride)
    with jax.ensure_compile_time_eval():   # operators concrete, as in classic_pipeline
      vol = csa.csa(full, setup, mask=mask, tau_rel=tau_rel, falloff=falloff)
    inten, depth = intensity_depth(vol, setup)
    return {"intensity": inten, "depth": depth}

  return fn


def learned_pipeline(mcfg, *, volume: bool = False) -> Callable:
  """``(params, x [B, F, T, h, w]) -> {"intensity", "depth" (, "volume")}`` of ``mcfg.module()``.

  The intensity is clamped to [0, 1] as in the main job's evaluation (USM's head is not).
  """
  import jax.numpy as jnp
  model = mcfg.module()

  def fn(params, x):
    out = model.apply({"params": params}, x)
    keys = ("intensity", "depth", "volume") if volume else ("intensity", "depth")
    return {k: jnp.clip(out[k], 0.0, 1.0) if k == "intensity" else out[k] for k in keys}

  return fn
