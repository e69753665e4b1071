"""The truth seen through the input's scan grid: what a reconstruction that is exact at the scan points reaches.

The networks and the classic methods read the scene through ``h x w`` scan points,
``stride // 2 + stride * i`` along each axis of the ``H x W`` grid (the model's convention,
:func:`nlosjax.models.blocks.underscan_indices`). The bounds here take the *true* intensity
and depth maps at those points and read them back to the full grid in one of two ways:

* ``bilinear``: the classic methods' reading of the sparse scan
  (:func:`nlosjax.evaluation.baselines.upsample_scan`, i.e.
  :func:`~nlosjax.models.blocks.interpolation_matrix`: bilinear, constant beyond the sampled
  span). Intensity is interpolated as it is. Depth is interpolated as a normalised
  convolution: the object indicator ``depth > 0`` and the depth are interpolated alike, a pixel
  is surface where the interpolated indicator reaches ``cut`` (chosen on validation by surface
  F1, as a classic method's surface threshold is), and its depth is the interpolated depth over
  the interpolated indicator (the indicator-weighted mean of the neighbouring samples' depths),
  so background samples do not pull an object's depth towards 0 m;
* ``nearest``: every full-grid pixel takes the value of its nearest scan point (each scan
  point fills its own ``stride x stride`` cell; a pixel half-way between two points takes the
  later one), intensity and depth alike.

Neither is a bound in the strict sense: every scan point of a confocal capture sees the whole
hidden scene, so a method with a prior on shapes can place detail between the scan points
that these readings cannot. They say how much of each object score survives sampling the
image itself at the input's density; the ceiling at this density is at least the better of
the two.
"""

from __future__ import annotations

import numpy as np

from nlosjax.models.blocks import interpolation_matrix, underscan_indices

__all__ = ["READINGS", "CUTS", "nearest_matrix", "reading_matrix", "sample", "bound_images"]

#: The two readings of the sampled truth.
READINGS = ("bilinear", "nearest")
#: Candidates for the bilinear reading's surface cut (share of the interpolated object indicator),
#: chosen on validation by mean surface F1 (ties: the earlier).
CUTS = (0.1, 0.3, 0.5, 0.7, 0.9)


def nearest_matrix(n_out: int, stride: int) -> np.ndarray:
  """``[n_out, n_in]`` 0/1 matrix: full-grid index ``r`` reads the scan point nearest to it.

  Scan point ``i`` sits at ``stride // 2 + stride * i``; the nearest to ``r`` is
  ``round((r - stride // 2) / stride)`` with halves rounded up, clamped to the sampled points
  (for even strides, ``r // stride``: each point fills its own ``stride``-wide cell).
  """
  n_in = underscan_indices(n_out, stride).size
  nearest = np.clip(np.floor((np.arange(n_out) - stride // 2) / stride + 0.5), 0, n_in - 1).astype(np.int64)
  m = np.zeros((n_out, n_in))
  m[np.arange(n_out), nearest] = 1.0
  return m


def reading_matrix(reading: str, n_out: int, stride: int) -> np.ndarray:
  """The ``[n_out, n_in]`` matrix of ``reading`` (:data:`READINGS`) along one axis."""
  if reading == "bilinear":
    return interpolation_matrix(n_out, stride)
  if reading == "nearest":
    return nearest_matrix(n_out, stride)
  raise ValueError(f"reading must be one of {READINGS}, got {reading!r}")


def sample(maps, stride: int) -> np.ndarray:
  """``[..., H, W] -> [..., h, w]``: the values at the scan points the input reads."""
  maps = np.asarray(maps)
  rows = underscan_indices(maps.shape[-2], stride)
  cols = underscan_indices(maps.shape[-1], stride)
  return maps[..., rows[:, None], cols[None, :]]


def _read(samples, reading, grid, stride):
  my = reading_matrix(reading, grid[0], stride)
  mx = reading_matrix(reading, grid[1], stride)
  return np.einsum("Hh,...hw,Ww->...HW", my, np.asarray(samples, np.float64), mx)


def bound_images(intensity, depth, stride: int, reading: str, cut: float = 0.5
                 ) -> tuple[np.ndarray, np.ndarray]:
  """The true maps sampled at the input's scan points and read back to the full grid.

  Args:
    intensity: ``[..., H, W]`` true intensity in [0, 1].
    depth: ``[..., H, W]`` true depth, metres, 0 at background.
    stride: the under-scan stride.
    reading: ``"bilinear"`` or ``"nearest"`` (module docstring).
    cut: surface where the read-back object indicator is at least ``cut`` (in (0, 1]; the
      nearest reading's indicator is 0 or 1, so any cut gives the same).
  Returns:
    ``(intensity [..., H, W] float32, depth [..., H, W] float32 metres, 0 at background)``.
  """
  if not 0.0 < cut <= 1.0:
    raise ValueError(f"cut must be in (0, 1], got {cut!r}")
  intensity, depth = np.asarray(intensity, np.float64), np.asarray(depth, np.float64)
  grid = intensity.shape[-2:]
  inten = _read(sample(intensity, stride), reading, grid, stride)
  d = sample(depth, stride)
  occupancy = _read((d > 0).astype(np.float64), reading, grid, stride)
  depth_sum = _read(d, reading, grid, stride)
  surface = occupancy >= cut - 1e-12
  out = np.where(surface, depth_sum / np.where(surface, occupancy, 1.0), 0.0)
  return inten.astype(np.float32), out.astype(np.float32)
