"""Under-scanning of the scan grid at load time: :func:`undersample`, the kept points and their Setup."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from nlosjax.physics.setup import Setup


def _check_stride(stride, offset):
  if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
    raise ValueError(f"stride must be an integer >= 1, got {stride!r}")
  if isinstance(offset, bool) or not isinstance(offset, (int, np.integer)) or not 0 <= offset < stride:
    raise ValueError(f"offset must be an integer in [0, stride={stride}), got {offset!r}")
  return int(stride), int(offset)


def undersample(x, stride: int, offset: int = 0):
  """Interval sampling of the scan grid: ``x[..., offset::stride, offset::stride]``.

  Args:
    x: ``[..., H, W]`` array (transient ``[..., T, H, W]`` or map).
    stride: keep every ``stride``-th scan point along rows and columns.
    offset: index of the first kept point, ``0 <= offset < stride``.
  Returns:
    ``[..., ceil((H - offset) / stride), ceil((W - offset) / stride)]`` view.
  """
  stride, offset = _check_stride(stride, offset)
  if np.ndim(x) < 2:
    raise ValueError(f"x must be at least [H, W], got shape {np.shape(x)}")
  return x[..., offset::stride, offset::stride]


def undersampled_positions(setup: Setup, stride: int, offset: int = 0):
  """``(y [h], x [w])`` float64 positions (metres) of the under-scanned points."""
  stride, offset = _check_stride(stride, offset)
  return setup.scan_y[offset::stride], setup.scan_x[offset::stride]


def undersampled_setup(setup: Setup, stride: int, offset: int = 0) -> Setup:
  """A Setup for the under-scanned grid: its spacing, ``(h, w)`` points, same bins.

  Its ``wall_size`` is ``(h - 1) * stride * spacing``; its grid is centred on
  the wall while the kept points are shifted by ``offset * spacing - (wall -
  new wall) / 2`` (e.g. -3.5 spacings for 128 -> 16 with offset 0); reconstructions
  on it are displaced by that much. Needs equal row and column spacing.
  """
  stride, offset = _check_stride(stride, offset)
  ys, xs = undersampled_positions(setup, stride, offset)
  if len(ys) < 2 or len(xs) < 2:
    raise ValueError(f"stride {stride} leaves fewer than 2 points per axis of grid {setup.grid}")
  span_y, span_x = ys[-1] - ys[0], xs[-1] - xs[0]
  if not math.isclose(span_y, span_x, rel_tol=1e-9):
    raise ValueError(f"under-scanned grid spans {span_y:.4g} m x {span_x:.4g} m; a Setup needs a"
                     " square span")
  return dataclasses.replace(setup, wall_size=float(span_x), grid=(len(ys), len(xs)))
