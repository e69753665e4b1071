"""Where the time goes: LCT split in three timed stages (:func:`lct_stages`,
:func:`lct_stage_executables`) and the network's volume stage alone
(:func:`network_volume_executable`).
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np


def lct_stages(setup, *, snr: float = 0.1) -> tuple[dict, Any]:
  """LCT (diffuse, Wiener ``snr``) split in three jittable stages; ``(stages, domain)``.

  ``input``: ``x [B, T, H, W]`` -> time window -> v-resampling -> lateral
  FFTs of the ``Nv`` rows; ``v-axis``: FFT of length ``Lv`` along v, Wiener
  filter, inverse FFT kept to ``Nu`` rows; ``output``: inverse lateral FFTs,
  u -> depth, clamp at 0 -> ``[B, Z, H, W]``. Composed, the same operations
  as :func:`nlosjax.physics.lct` (:func:`~nlosjax.physics.operators.lct_apply`),
  split so each can be timed.
  """
  import jax.numpy as jnp

  from nlosjax.physics.operators import filter_v_axis, lct_filter, lct_operators
  ops = lct_operators(setup, 3.0, oversample=1)
  filt = lct_filter(ops, snr)
  dom = ops.domain
  _, h2, w2 = dom.fft_shape
  H, W = setup.grid
  t0, t1 = dom.t

  def stage_in(x):
    v = jnp.einsum("vt,bthw->bvhw", ops.to_v, x[:, t0:t1], precision="highest")
    return jnp.fft.fft(jnp.fft.rfft(v, n=w2, axis=3), n=h2, axis=2)

  def stage_v(spec):
    return filter_v_axis(spec, filt, dom, axis=1)

  def stage_out(spec):
    vol = jnp.fft.irfft(jnp.fft.ifft(spec, axis=2)[:, :, :H], n=w2, axis=3)[..., :W]
    return jnp.maximum(jnp.einsum("zu,buhw->bzhw", ops.to_z, vol, precision="highest"), 0.0)

  return {"input": stage_in, "v-axis": stage_v, "output": stage_out}, dom


def lct_stage_executables(setup, x_full: np.ndarray) -> tuple[dict, dict]:
  """Jitted :func:`lct_stages` with their inputs for ``x_full [B, T, H, W]``.

  Returns ``({stage: (fn, args)}, {"nt", "nv", "lv", "nu"})`` (the domain's bin counts).
  """
  import jax
  stages, dom = lct_stages(setup)
  fns = {k: jax.jit(f) for k, f in stages.items()}
  x = jax.device_put(x_full)
  a = fns["input"](x)
  b = fns["v-axis"](a)
  args = {"input": (x,), "v-axis": (a,), "output": (b,)}
  sizes = {"nt": dom.t[1] - dom.t[0], "nv": dom.num_v, "lv": dom.fft_shape[0], "nu": dom.num_u}
  return {k: (fns[k], args[k]) for k in fns}, sizes


def network_volume_executable(mcfg, params, batch: int) -> tuple[Callable, tuple, int]:
  """The network's volume stage alone, jitted, with a ``[batch, Tw, H, W]`` input.

  :class:`~nlosjax.models.blocks.VolumeReconstruction` (feature extraction,
  physics layer, refinement) with the trained ``params["volume"]``. Returns
  ``(fn, args, Tw)``.
  """
  import jax
  import jax.numpy as jnp

  from nlosjax.models import blocks
  vol = blocks.VolumeReconstruction(**mcfg.volume_kwargs())
  a, b = mcfg.time_window
  H, W = mcfg.setup.grid
  xt = jax.random.uniform(jax.random.key(0), (batch, b - a, H, W), jnp.float32)
  fn = jax.jit(lambda p, t: vol.apply({"params": p}, t)["intensity"])
  return fn, (params["volume"], xt), b - a
