"""From a volume to the images people look at: intensity in [0, 1] and metric depth.

Recipe (nlos3d, NLOST, O'Toole's ``cnlos``): clamp the volume at 0; the
intensity image is the maximum over depth, divided by its maximum over the
image (per example); the depth map is the nominal depth ``z_k`` (metres) of
that maximum. *Background rule*: pixels whose intensity is below
``threshold`` (default 0.1 of the image maximum, as the public scripts mask)
get ``background_depth`` (default 0 m, the value the ground-truth depth maps
of the public datasets use for "no surface"). An all-zero volume gives an
all-zero intensity image and an all-background depth map.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from nlosjax.physics.setup import Setup


def intensity_depth(volume, setup: Setup, *, threshold: float = 0.1,
                    background_depth: float = 0.0) -> tuple[jax.Array, jax.Array]:
  """Intensity image and depth map of a volume.

  Args:
    volume: ``[..., Z, H, W]`` (any real values; negatives are clamped to 0).
    setup: the capture (``setup.depths`` gives each bin's depth).
    threshold: intensity below which a pixel is background, in [0, 1).
    background_depth: depth, metres, written at background pixels.
  Returns:
    ``(intensity [..., H, W] float32 in [0, 1], depth [..., H, W] float32 metres)``.
  """
  if not isinstance(setup, Setup):
    raise ValueError(f"setup must be a nlosjax.physics.Setup, got {type(setup).__name__}")
  setup.check_volume(volume)
  if not 0.0 <= threshold < 1.0:
    raise ValueError(f"threshold must be in [0, 1), got {threshold!r}")
  vol = jnp.asarray(volume, jnp.float32)
  vol = jnp.where(jnp.isfinite(vol), jnp.maximum(vol, 0.0), 0.0)
  mip = jnp.max(vol, axis=-3)
  peak = jnp.max(mip, axis=(-2, -1), keepdims=True)
  intensity = jnp.where(peak > 0, mip / jnp.where(peak > 0, peak, 1.0), 0.0)
  depths = jnp.asarray(setup.depths, jnp.float32)
  depth = depths[jnp.argmax(vol, axis=-3)]
  depth = jnp.where(intensity >= max(threshold, 1e-30), depth, jnp.float32(background_depth))
  return jnp.clip(intensity, 0.0, 1.0), depth
