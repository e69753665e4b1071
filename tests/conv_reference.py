"""Independent references for ``nlosjax.models.conv.Conv3D`` (zero padding): XLA's own "SAME"
convolution (``padding="SAME"``, so not the module's padding amounts) and a NumPy loop over
output voxels and taps from the definition of "SAME" (output ``ceil(T / s)``; the
``max((out - 1) s + (k - 1) d + 1 - T, 0)`` padded zeros split with the smaller half first,
``(k - 1) / 2`` on each side in H and W)."""

import jax
import numpy as np


def same_conv3d(x, kernel, bias=None, stride=1, dilation=1):
  """``[N, T, H, W, C] * [kt, kh, kw, C, F]`` "SAME", strided and dilated along T only."""
  y = jax.lax.conv_general_dilated(x, kernel, (stride, 1, 1), "SAME", rhs_dilation=(dilation, 1, 1),
                                   dimension_numbers=("NDHWC", "DHWIO", "NDHWC"),
                                   precision=jax.lax.Precision.HIGHEST)
  return y if bias is None else y + bias


def loop_conv3d(x, kernel, bias=None, stride=1, dilation=1):
  """The same in float64, one output voxel and tap at a time."""
  x, kernel = np.asarray(x, np.float64), np.asarray(kernel, np.float64)
  n, t, h, w, _ = x.shape
  kt, kh, kw, _, f = kernel.shape
  out = -(-t // stride)
  lo = max((out - 1) * stride + (kt - 1) * dilation + 1 - t, 0) // 2
  y = np.zeros((n, out, h, w, f))
  for o in range(out):
    for a in range(kt):
      ti = o * stride - lo + a * dilation
      if not 0 <= ti < t:
        continue
      for yy in range(h):
        for b in range(kh):
          yi = yy + b - kh // 2
          if not 0 <= yi < h:
            continue
          for xx in range(w):
            for c in range(kw):
              xi = xx + c - kw // 2
              if 0 <= xi < w:
                y[:, o, yy, xx] += x[:, ti, yi, xi] @ kernel[a, b, c]
  return y if bias is None else y + np.asarray(bias, np.float64)
