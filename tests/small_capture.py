"""A small noisy confocal capture shared by the evaluation and trade-study tests."""

import numpy as np

from nlosjax import physics


def three_patch_capture(seed: int = 0):
  """Three frames of one bright patch each, rendered and Poisson-sampled.

  Returns ``(setup, full, albedo)``: a 1 m wall, 12 x 12 scan points, 32 bins
  of 64 ps; ``full`` the counts ``[3, 32, 12, 12]`` (200 photons per unit of
  the clean transient, 0.05 background per bin); ``albedo`` ``[3, 32, 12, 12]``
  with one patch per frame at depth bin ``12 + 3 i``.
  """
  setup = physics.Setup(wall_size=1.0, grid=(12, 12), bin_width=64e-12, num_bins=32)
  rng = np.random.default_rng(seed)
  albedo = np.zeros((3, 32, 12, 12), np.float32)
  for i in range(3):
    albedo[i, 12 + 3 * i, 3:9, 3 + 2 * i:5 + 2 * i] = 1.0
  clean = np.asarray(physics.render(albedo, setup)) * 200
  full = rng.poisson(clean + 0.05).astype(np.float32)
  return setup, full, albedo
