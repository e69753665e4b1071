"""Image and depth-map quality metrics: PSNR, SSIM, RMSE, MAD, and object-aware depth scores.

Every function takes ``pred`` and ``target`` of the same shape ``[..., H, W]``
(leading batch dimensions allowed) and returns one value per image, ``[...]``;
the temporal scores (:data:`TEMPORAL_METRICS`) take sequences ``[..., F, H, W]``
and return one value per consecutive pair, ``[..., F - 1]`` (or per sequence with
``pooled=True``). Intensities are in ``[0, 1]`` (``data_range`` 1), depths in
metres; sums run in float32 (float64 for float64 inputs). Pure ``jax.numpy``:
jit, vmap and grad apply; concrete inputs are checked for NaN, masks for 0/1.

The object-aware scores (:func:`surface_scores`: ``rmse_object``, ``mad_object``,
``recall``, ``precision``, ``f1``) score the objects themselves, where
whole-image depth RMSE/MAD reward writing 0 m everywhere but the brightest object.

The definitions (masks, the PSNR cap, SSIM's scikit-image settings, behaviour
under ``jit`` with NaN and inf, what counts as surface, the temporal scores) are
in ``docs/evaluation.md``, "Metric definitions".
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["PSNR_CAP_DB", "SURFACE_MIN_DEPTH", "OBJECT_METRICS", "TEMPORAL_METRICS", "psnr", "ssim",
           "rmse", "mad", "surface", "surface_scores", "rmse_object", "mad_object", "recall", "precision",
           "f1", "intensity_mae_object", "psnr_zero", "psnr_balanced", "psnr_balanced_zero",
           "temporal_rmse", "temporal_psnr",
           "temporal_rmse_object"]

PSNR_CAP_DB = 100.0
"""PSNR (dB) returned for identical images: MSE is floored at
``data_range**2 * 10**(-PSNR_CAP_DB / 10)``."""

_PSNR_MSE_FLOOR = 10.0 ** (-PSNR_CAP_DB / 10.0)  # relative to data_range**2

_GAUSSIAN_TRUNCATE = 3.5  # scikit-image's truncation for gaussian_weights=True

# "Surfaces" and "Temporal consistency" below are sections of docs/evaluation.md.
SURFACE_MIN_DEPTH = 0.1
"""Depth (metres) from which a reconstructed pixel counts as surface (see "Surfaces")."""

OBJECT_METRICS = ("rmse_object", "mad_object", "recall", "precision", "f1")
"""The keys of :func:`surface_scores`, in table order."""

TEMPORAL_METRICS = ("temporal_rmse", "temporal_psnr", "temporal_rmse_object")
"""The temporal-consistency scores (see "Temporal consistency"), in table order."""


# --------------------------------------------------------------------------
# Validation (Python level, before any compilation).


def _is_concrete(x) -> bool:
  return not isinstance(x, jax.core.Tracer)


def _check_images(fn: str, pred, target, mask) -> None:
  """Shape, rank, NaN and mask checks shared by every metric."""
  pred_shape = tuple(np.shape(pred))
  target_shape = tuple(np.shape(target))
  if len(pred_shape) < 2:
    raise ValueError(
        f"{fn}: pred must have rank >= 2 ([..., H, W]), got shape {pred_shape}")
  if target_shape != pred_shape:
    raise ValueError(
        f"{fn}: target has shape {target_shape} but pred has shape {pred_shape}; "
        "they must match")
  if mask is not None:
    mask_shape = tuple(np.shape(mask))
    if mask_shape != pred_shape:
      raise ValueError(
          f"{fn}: mask has shape {mask_shape} but pred has shape {pred_shape}; "
          "they must match")
  for name, x in (("pred", pred), ("target", target)):
    if _is_concrete(x):
      a = np.asarray(x)
      if np.issubdtype(a.dtype, np.complexfloating):
        raise ValueError(f"{fn}: {name} must be real, got dtype {a.dtype}")
      if a.dtype.kind not in "biu" and np.isnan(a).any():
        raise ValueError(f"{fn}: {name} contains NaN")


def _check_mask_values(fn: str, mask, crop: int = 0) -> None:
  """A concrete mask must be 0/1 and select >= 1 pixel per image (after crop)."""
  if mask is None or not _is_concrete(mask):
    return
  m = np.asarray(mask)
  if m.dtype != np.bool_:
    if not np.all((m == 0) | (m == 1)):
      raise ValueError(f"{fn}: mask must be boolean or contain only 0 and 1")
    m = m != 0
  h, w = m.shape[-2:]
  inner = m[..., crop:h - crop, crop:w - crop]
  if not inner.any(axis=(-2, -1)).all():
    where = (f" inside the {crop}-pixel border crop" if crop else "")
    raise ValueError(f"{fn}: mask selects no pixel{where} for at least one image")


def _check_scalar(fn: str, name: str, value, *, allow_zero: bool) -> None:
  """A concrete ``value`` must be finite and > 0 (>= 0 with ``allow_zero``)."""
  if not _is_concrete(value):
    return
  v = np.asarray(value)
  if not np.issubdtype(v.dtype, np.number) or np.issubdtype(v.dtype, np.complexfloating):
    raise ValueError(f"{fn}: {name} must be a real number, got {value!r}")
  ok = np.isfinite(v) & ((v >= 0) if allow_zero else (v > 0))
  if not np.all(ok):
    bound = ">= 0" if allow_zero else "> 0"
    raise ValueError(f"{fn}: {name} must be finite and {bound}, got {value!r}")


# --------------------------------------------------------------------------
# Shared pieces (traced).


def _compute_dtype(pred, target):
  """float32, or float64 when an input is float64 (x64 mode)."""
  return jnp.promote_types(jnp.result_type(pred, target), jnp.float32)


def _masked_mean(x, mask):
  """Mean of ``x [..., H, W]`` over H, W, or over the pixels where ``mask``.

  With a mask, an image with no selected pixel averages to 0.
  """
  if mask is None:
    return jnp.mean(x, axis=(-2, -1))
  m = mask.astype(bool)
  total = jnp.sum(jnp.where(m, x, 0), axis=(-2, -1))
  count = jnp.sum(m, axis=(-2, -1), dtype=x.dtype)
  return total / jnp.maximum(count, 1)


def _prepare(pred, target, mask):
  pred = jnp.asarray(pred)
  target = jnp.asarray(target)
  dtype = _compute_dtype(pred, target)
  mask = None if mask is None else jnp.asarray(mask)
  return pred.astype(dtype), target.astype(dtype), mask, dtype


@jax.jit
def _mse(pred, target, mask):
  return _masked_mean(jnp.square(pred - target), mask)


@jax.jit
def _psnr(pred, target, mask, data_range):
  range_sq = jnp.square(data_range)
  mse = _mse(pred, target, mask)
  return 10.0 * jnp.log10(range_sq / jnp.maximum(mse, range_sq * _PSNR_MSE_FLOOR))


def _sqrt_guarded(mse):
  """``sqrt(mse)`` of a mean square: exactly 0 at 0 with a zero (finite) gradient there.

  A where-guard, and not a plain ``mse > 0`` fallback to 0: NaN is not ``> 0``,
  so such a fallback would turn NaN into 0. Here NaN stays NaN, ``inf`` gives
  ``inf`` and a negative value NaN, as ``sqrt`` does; only 0 is special-cased.
  """
  positive = mse > 0
  root = jnp.sqrt(jnp.where(positive, mse, 1.0))       # no sqrt'(0) = inf in the gradient
  return jnp.where(positive, root, jnp.where(mse == 0, 0.0, jnp.nan))


@jax.jit
def _rmse(pred, target, mask):
  return _sqrt_guarded(_mse(pred, target, mask))


@jax.jit
def _mad(pred, target, mask):
  return _masked_mean(jnp.abs(pred - target), mask)


def _gaussian_taps(sigma: float) -> tuple[float, ...]:
  """scipy.ndimage's 1D Gaussian at ``truncate = 3.5``, normalised to sum 1."""
  radius = int(_GAUSSIAN_TRUNCATE * sigma + 0.5)
  x = np.arange(-radius, radius + 1, dtype=np.float64)
  taps = np.exp(-0.5 * (x / sigma) ** 2)
  taps /= taps.sum()
  return tuple(float(t) for t in taps)


def _gaussian_filter_2d(x, taps):
  """Separable Gaussian filter over the last two axes, symmetric padding.

  Matches ``scipy.ndimage.gaussian_filter(mode="reflect")`` on each image.
  Written as shifted, weighted slices (no convolution primitive): exact
  float32 arithmetic on every backend.
  """
  radius = (len(taps) - 1) // 2
  h, w = x.shape[-2:]
  pad = [(0, 0)] * (x.ndim - 2) + [(radius, radius), (radius, radius)]
  xp = jnp.pad(x, pad, mode="symmetric")
  rows = sum(t * xp[..., k:k + h, :] for k, t in enumerate(taps))
  return sum(t * rows[..., :, k:k + w] for k, t in enumerate(taps))


@functools.partial(jax.jit, static_argnames=("win_size", "sigma"))
def _ssim(pred, target, mask, data_range, k1, k2, *, win_size, sigma):
  taps = _gaussian_taps(sigma)
  # Local statistics are shift-invariant: subtract a per-image constant first
  # so that E[x^2] - E[x]^2 does not cancel catastrophically in float32.
  shift = 0.5 * (jnp.mean(pred, axis=(-2, -1), keepdims=True)
                 + jnp.mean(target, axis=(-2, -1), keepdims=True))
  shift = jax.lax.stop_gradient(shift)
  x = pred - shift
  y = target - shift
  stats = _gaussian_filter_2d(jnp.stack([x, y, x * x, y * y, x * y], axis=-3), taps)
  mx, my, mxx, myy, mxy = (stats[..., i, :, :] for i in range(5))
  var_x = mxx - mx * mx
  var_y = myy - my * my
  cov_xy = mxy - mx * my
  mu_x = mx + shift
  mu_y = my + shift

  c1 = jnp.square(k1 * data_range)[..., None, None]
  c2 = jnp.square(k2 * data_range)[..., None, None]
  ssim_map = ((2.0 * mu_x * mu_y + c1) * (2.0 * cov_xy + c2)
              / ((mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2)))

  crop = (win_size - 1) // 2
  h, w = ssim_map.shape[-2:]
  ssim_map = ssim_map[..., crop:h - crop, crop:w - crop]
  if mask is None:
    return jnp.mean(ssim_map, axis=(-2, -1))
  m = mask[..., crop:h - crop, crop:w - crop].astype(bool)
  count = jnp.sum(m, axis=(-2, -1), dtype=ssim_map.dtype)
  total = jnp.sum(jnp.where(m, ssim_map, 0), axis=(-2, -1))
  return jnp.where(count > 0, total / jnp.maximum(count, 1), 1.0)


# --------------------------------------------------------------------------
# Public API.


def psnr(pred, target, *, mask=None, data_range=1.0):
  """Peak signal-to-noise ratio, in dB, of each image.

  ``PSNR = 10 * log10(data_range**2 / max(MSE, data_range**2 * 1e-10))``
  with ``MSE = mean((pred - target)**2)`` over ``H, W`` (over the pixels
  where ``mask`` is true when a mask is given). Matches
  ``skimage.metrics.peak_signal_noise_ratio(target, pred,
  data_range=data_range)`` except at (near-)zero error: identical images give
  the finite cap :data:`PSNR_CAP_DB` = 100 dB, never ``inf``/NaN.

  Args:
    pred: ``[..., H, W]`` real array (float32 or cast to it), e.g. an
      intensity image in ``[0, 1]``.
    target: ``[..., H, W]``, same shape as ``pred``. Symmetric in the two.
    mask: optional ``[..., H, W]`` boolean (or 0/1) array, same shape. A
      concrete mask selecting no pixel of some image raises ``ValueError``;
      under ``jit`` such an image has MSE 0 and scores the 100 dB cap.
    data_range: max - min of the possible values (1 for images in
      ``[0, 1]``); a positive scalar or an array broadcastable to ``[...]``.

  Returns:
    ``[...]`` float32 array, dB, at most ``PSNR_CAP_DB``.

  Raises:
    ValueError: shapes of ``pred``/``target``/``mask`` differ, rank < 2, NaN
      in a concrete input, a concrete mask not 0/1 or selecting no pixel of
      some image, ``data_range`` not finite and > 0.
  """
  _check_images("psnr", pred, target, mask)
  _check_mask_values("psnr", mask)
  _check_scalar("psnr", "data_range", data_range, allow_zero=False)
  pred, target, mask, dtype = _prepare(pred, target, mask)
  return _psnr(pred, target, mask, jnp.asarray(data_range, dtype))


def ssim(pred, target, *, mask=None, data_range=1.0, win_size=11, sigma=1.5,
         k1=0.01, k2=0.03):
  """Structural similarity (Gaussian-weighted, Wang et al. 2004) of each image.

  Local statistics use a normalised Gaussian window ``g`` (std ``sigma``
  pixels, truncated at radius ``int(3.5 * sigma + 0.5)``: 11 taps for
  ``sigma = 1.5``), applied separably with symmetric padding
  (``d c b a | a b c d``) at the borders::

    mu_x = g * x,   var_x = g * x**2 - mu_x**2,   cov = g * (x y) - mu_x mu_y
    SSIM_map = (2 mu_x mu_y + C1) (2 cov + C2)
               / ((mu_x**2 + mu_y**2 + C1) (var_x + var_y + C2))
    C1 = (k1 * data_range)**2,  C2 = (k2 * data_range)**2

  (population, not sample, covariances). The map is cropped by
  ``(win_size - 1) // 2`` pixels on each side and averaged (over the masked
  pixels of the cropped area when ``mask`` is given). This is exactly
  ``skimage.metrics.structural_similarity(pred, target, win_size=win_size,
  gaussian_weights=True, sigma=sigma, use_sample_covariance=False,
  data_range=data_range, K1=k1, K2=k2)`` per image, in float32. As in
  scikit-image, ``win_size`` sets only the border crop and the minimum image
  size; the Gaussian's extent follows from ``sigma``.

  Args:
    pred: ``[..., H, W]`` real array, e.g. an intensity image in ``[0, 1]``;
      ``H, W >= win_size``.
    target: ``[..., H, W]``, same shape. Symmetric in the two.
    mask: optional ``[..., H, W]`` boolean (or 0/1) array, same shape. It
      selects which SSIM-map pixels are averaged; the filtering always sees
      the full images. A concrete mask with no pixel inside the cropped area
      of some image raises ``ValueError``; under ``jit`` that image scores 1.
    data_range: max - min of the possible values; positive scalar or array
      broadcastable to ``[...]``.
    win_size: odd integer >= 1 (static); border crop is ``(win_size-1)//2``.
    sigma: Gaussian standard deviation in pixels, > 0 (static).
    k1, k2: SSIM constants, >= 0.

  Returns:
    ``[...]`` float32 array, unitless, in ``[-1, 1]``; 1 (to float32
    rounding) for identical images.

  Raises:
    ValueError: shapes differ, rank < 2, ``H`` or ``W`` < ``win_size``, NaN in
      a concrete input, a bad concrete mask, bad ``win_size``/``sigma``/
      ``data_range``/``k1``/``k2``.
  """
  _check_images("ssim", pred, target, mask)
  if isinstance(win_size, bool) or not isinstance(win_size, (int, np.integer)):
    raise ValueError(f"ssim: win_size must be an odd integer, got {win_size!r}")
  win_size = int(win_size)
  if win_size < 1 or win_size % 2 == 0:
    raise ValueError(f"ssim: win_size must be an odd integer >= 1, got {win_size}")
  try:
    sigma = float(sigma)
  except (TypeError, jax.errors.ConcretizationTypeError) as err:
    raise ValueError(f"ssim: sigma must be a Python number, got {sigma!r}") from err
  if not (math.isfinite(sigma) and sigma > 0):
    raise ValueError(f"ssim: sigma must be finite and > 0, got {sigma!r}")
  h, w = np.shape(pred)[-2:]
  if h < win_size or w < win_size:
    raise ValueError(
        f"ssim: images of {h}x{w} pixels are smaller than win_size={win_size}; "
        f"H and W must be >= {win_size}")
  _check_mask_values("ssim", mask, crop=(win_size - 1) // 2)
  _check_scalar("ssim", "data_range", data_range, allow_zero=False)
  _check_scalar("ssim", "k1", k1, allow_zero=True)
  _check_scalar("ssim", "k2", k2, allow_zero=True)
  pred, target, mask, dtype = _prepare(pred, target, mask)
  return _ssim(pred, target, mask, jnp.asarray(data_range, dtype),
               jnp.asarray(k1, dtype), jnp.asarray(k2, dtype),
               win_size=win_size, sigma=sigma)


def rmse(pred, target, *, mask=None):
  """Root mean squared error of each image, in the units of the inputs.

  ``RMSE = sqrt(mean((pred - target)**2))`` over ``H, W`` (over the pixels
  where ``mask`` is true when a mask is given); metres for depth maps. The
  square root is guarded: zero error gives exactly 0 with a zero (finite)
  gradient, not NaN. The guard does not touch NaN: under ``jit`` (where the
  NaN check cannot run) an image holding a NaN scores NaN, and one holding
  ``inf`` scores ``inf``.

  Args:
    pred: ``[..., H, W]`` real array (intensity image, or depth map in
      metres).
    target: ``[..., H, W]``, same shape and units.
    mask: optional ``[..., H, W]`` boolean (or 0/1) array, same shape, e.g.
      the pixels with a valid ground-truth depth. A concrete mask selecting no
      pixel of some image raises ``ValueError``; under ``jit`` that image
      scores 0.

  Returns:
    ``[...]`` float32 array, >= 0 (NaN for a traced input holding NaN), same
    units as the inputs.

  Raises:
    ValueError: shapes differ, rank < 2, NaN in a concrete input, a concrete
      mask not 0/1 or selecting no pixel of some image.
  """
  _check_images("rmse", pred, target, mask)
  _check_mask_values("rmse", mask)
  pred, target, mask, _ = _prepare(pred, target, mask)
  return _rmse(pred, target, mask)


def mad(pred, target, *, mask=None):
  """Mean absolute difference of each image, in the units of the inputs.

  ``MAD = mean(|pred - target|)`` over ``H, W`` (over the pixels where
  ``mask`` is true when a mask is given); metres for depth maps.

  Args:
    pred: ``[..., H, W]`` real array (intensity image, or depth map in
      metres).
    target: ``[..., H, W]``, same shape and units.
    mask: optional ``[..., H, W]`` boolean (or 0/1) array, same shape. A
      concrete mask selecting no pixel of some image raises ``ValueError``;
      under ``jit`` that image scores 0.

  Returns:
    ``[...]`` float32 array, >= 0, same units as the inputs.

  Raises:
    ValueError: shapes differ, rank < 2, NaN in a concrete input, a concrete
      mask not 0/1 or selecting no pixel of some image.
  """
  _check_images("mad", pred, target, mask)
  _check_mask_values("mad", mask)
  pred, target, mask, _ = _prepare(pred, target, mask)
  return _mad(pred, target, mask)


# --------------------------------------------------------------------------
# Object-aware depth scores.


def surface(depth, *, min_depth: float = SURFACE_MIN_DEPTH):
  """Pixels reconstructed as surface: ``depth >= min_depth``.

  Args:
    depth: ``[..., H, W]`` depth map, metres.
    min_depth: metres (default :data:`SURFACE_MIN_DEPTH`), > 0.
  Returns:
    ``[..., H, W]`` bool.
  """
  _check_scalar("surface", "min_depth", min_depth, allow_zero=False)
  return jnp.asarray(depth) >= min_depth


def _true_surface(target_depth):
  """True surface pixels of a ground-truth depth map: depth > 0 (docs/evaluation.md, "Surfaces")."""
  return target_depth > 0


@jax.jit
def _surface_scores(pred, target, min_depth):
  nan = jnp.array(jnp.nan, pred.dtype)
  truth = _true_surface(target)
  found = surface(pred, min_depth=min_depth)
  axes = (-2, -1)
  tp = jnp.sum(truth & found, axis=axes, dtype=pred.dtype)
  fn = jnp.sum(truth & ~found, axis=axes, dtype=pred.dtype)
  fp = jnp.sum(~truth & found, axis=axes, dtype=pred.dtype)
  n_true = tp + fn
  # Comparisons map NaN to False (background): flag such images and return NaN for them.
  has_nan = jnp.any(jnp.isnan(pred) | jnp.isnan(target), axis=axes)

  def ratio(num, den):      # den counts pixels: never NaN itself
    return jnp.where((den > 0) & ~has_nan, num / jnp.maximum(den, 1), nan)

  err = jnp.where(truth, pred - target, 0)
  mse = ratio(jnp.sum(jnp.square(err), axis=axes), n_true)
  return {
      "rmse_object": _sqrt_guarded(mse),
      "mad_object": ratio(jnp.sum(jnp.abs(err), axis=axes), n_true),
      "recall": ratio(tp, n_true),
      "precision": ratio(tp, tp + fp),
      "f1": ratio(2 * tp, 2 * tp + fp + fn),
  }


def surface_scores(pred_depth, target_depth, *, min_depth: float = SURFACE_MIN_DEPTH) -> dict:
  """Object-aware depth scores of each image (docs/evaluation.md, "Surfaces").

  Args:
    pred_depth: ``[..., H, W]`` reconstructed depth map, metres (background
      below ``min_depth``, e.g. 0 m).
    target_depth: ``[..., H, W]`` true depth map, metres, 0 at background.
    min_depth: metres from which a reconstructed pixel is surface.

  Returns:
    ``{name: [...] float32}`` for the names in :data:`OBJECT_METRICS`:
    ``rmse_object``, ``mad_object`` (metres, over true surface pixels),
    ``recall``, ``precision``, ``f1`` (in [0, 1]). NaN where the score's
    denominator is empty, and every score NaN for an image holding a NaN
    (traced input; docs/evaluation.md, "Conventions").

  Raises:
    ValueError: shapes differ, rank < 2, NaN in a concrete input, ``min_depth`` <= 0.
  """
  _check_images("surface_scores", pred_depth, target_depth, None)
  _check_scalar("surface_scores", "min_depth", min_depth, allow_zero=False)
  pred, target, _, dtype = _prepare(pred_depth, target_depth, None)
  scores = _surface_scores(pred, target, jnp.asarray(min_depth, dtype))
  return {k: scores[k] for k in OBJECT_METRICS}      # jit returns keys sorted


def rmse_object(pred_depth, target_depth):
  """Depth RMSE (metres) over each image's true surface pixels; ``[...]``, NaN if it has none.

  ``pred_depth``, ``target_depth``: ``[..., H, W]`` metres (0 = background in the target).
  """
  return surface_scores(pred_depth, target_depth)["rmse_object"]


@jax.jit
def _intensity_mae_object(pred, target, depth):
  truth = _true_surface(depth)
  n = jnp.sum(truth, axis=(-2, -1))
  total = jnp.sum(jnp.where(truth, jnp.abs(pred - target), 0), axis=(-2, -1))
  has_nan = jnp.any(jnp.isnan(pred) | jnp.isnan(target), axis=(-2, -1))
  return jnp.where((n > 0) & ~has_nan, total / jnp.maximum(n, 1), jnp.array(jnp.nan, pred.dtype))


def intensity_mae_object(pred_intensity, target_intensity, target_depth):
  """Intensity mean absolute error over each image's true object pixels; ``[...]``, NaN if it has none.

  The object pixels are the ground truth's surface (``target_depth > 0``, docs/evaluation.md,
  "Surfaces"), so a reconstruction that is dark everywhere scores the objects' mean true
  intensity, however clean its background: the score intensity PSNR cannot give.

  Args:
    pred_intensity, target_intensity: ``[..., H, W]`` in [0, 1].
    target_depth: ``[..., H, W]`` true depth, metres, 0 at background.
  Raises:
    ValueError: shapes differ, rank < 2, NaN in a concrete input.
  """
  _check_images("intensity_mae_object", pred_intensity, target_intensity, None)
  _check_images("intensity_mae_object", target_intensity, target_depth, None)
  pred, target, _, dtype = _prepare(pred_intensity, target_intensity, None)
  return _intensity_mae_object(pred, target, jnp.asarray(target_depth, dtype))


def psnr_zero(target_intensity):
  """The all-zero image's intensity PSNR (dB) against each target: the floor a dark reconstruction reaches.

  ``target_intensity``: ``[..., H, W]`` in [0, 1]; returns ``[...]``
  (:func:`psnr` of zeros, so an all-dark target gives the cap :data:`PSNR_CAP_DB`).
  """
  return psnr(jnp.zeros_like(jnp.asarray(target_intensity)), target_intensity)


@jax.jit
def _psnr_balanced(pred, target, depth):
  truth = _true_surface(depth)
  sq = jnp.square(pred - target)
  n_fg = jnp.sum(truth, axis=(-2, -1))
  n_bg = jnp.sum(~truth, axis=(-2, -1))
  mse_fg = jnp.sum(jnp.where(truth, sq, 0), axis=(-2, -1)) / jnp.maximum(n_fg, 1)
  mse_bg = jnp.sum(jnp.where(truth, 0, sq), axis=(-2, -1)) / jnp.maximum(n_bg, 1)
  mse = jnp.where((n_fg > 0) & (n_bg > 0), 0.5 * (mse_fg + mse_bg), jnp.where(n_fg > 0, mse_fg, mse_bg))
  out = -10.0 * jnp.log10(jnp.maximum(mse, _PSNR_MSE_FLOOR))
  has_nan = jnp.any(jnp.isnan(pred) | jnp.isnan(target), axis=(-2, -1))
  return jnp.where(has_nan, jnp.array(jnp.nan, pred.dtype), out.astype(pred.dtype))


def psnr_balanced(pred_intensity, target_intensity, target_depth):
  """Intensity PSNR (dB, peak 1) with object and background pixels weighted equally, per image.

  ``PSNR = -10 log10((MSE_object + MSE_background) / 2)``, each MSE the mean over its own
  pixels (the object pixels are the ground truth's surface, ``target_depth > 0``; an image
  with only one kind scores that kind's MSE). The whole-image PSNR weights each pixel alike,
  so on scenes whose objects cover a tenth of the image a dark image scores well; here the
  objects weigh half, and an image dark on them scores :func:`psnr_balanced_zero` (about
  ``-10 log10(mean object intensity^2 / 2)``), however clean its background. Identical images
  give :data:`PSNR_CAP_DB`.

  Args:
    pred_intensity, target_intensity: ``[..., H, W]`` in [0, 1].
    target_depth: ``[..., H, W]`` true depth, metres, 0 at background.
  Returns:
    ``[...]`` float32, dB (NaN where an input image holds NaN).
  Raises:
    ValueError: shapes differ, rank < 2, NaN in a concrete input.
  """
  _check_images("psnr_balanced", pred_intensity, target_intensity, None)
  _check_images("psnr_balanced", target_intensity, target_depth, None)
  pred, target, _, dtype = _prepare(pred_intensity, target_intensity, None)
  return _psnr_balanced(pred, target, jnp.asarray(target_depth, dtype))


def psnr_balanced_zero(target_intensity, target_depth):
  """The all-zero image's :func:`psnr_balanced` against each target: the floor of a dark reconstruction."""
  return psnr_balanced(jnp.zeros_like(jnp.asarray(target_intensity)), target_intensity, target_depth)


def mad_object(pred_depth, target_depth):
  """Depth mean absolute difference (metres) over each image's true surface pixels; ``[...]``.

  ``pred_depth``, ``target_depth``: ``[..., H, W]`` metres. NaN for an image with no surface.
  """
  return surface_scores(pred_depth, target_depth)["mad_object"]


def recall(pred_depth, target_depth, *, min_depth: float = SURFACE_MIN_DEPTH):
  """Share of true surface pixels reconstructed as surface; ``[...]`` in [0, 1], NaN if none.

  ``pred_depth``, ``target_depth``: ``[..., H, W]`` metres.
  """
  return surface_scores(pred_depth, target_depth, min_depth=min_depth)["recall"]


def precision(pred_depth, target_depth, *, min_depth: float = SURFACE_MIN_DEPTH):
  """Share of reconstructed surface pixels that are true surface; ``[...]``, NaN if none.

  ``pred_depth``, ``target_depth``: ``[..., H, W]`` metres.
  """
  return surface_scores(pred_depth, target_depth, min_depth=min_depth)["precision"]


def f1(pred_depth, target_depth, *, min_depth: float = SURFACE_MIN_DEPTH):
  """Harmonic mean of recall and precision, ``2 TP / (2 TP + FP + FN)``; ``[...]`` in [0, 1].

  ``pred_depth``, ``target_depth``: ``[..., H, W]`` metres. NaN only when neither
  image has any surface pixel.
  """
  return surface_scores(pred_depth, target_depth, min_depth=min_depth)["f1"]


# --------------------------------------------------------------------------
# Temporal consistency: the change between consecutive frames against the true change.


def _check_sequences(fn: str, pred, target, pooled) -> None:
  """Rank >= 3, >= 2 frames, matching shapes, no concrete NaN; ``pooled`` a bool."""
  shape = tuple(np.shape(pred))
  if len(shape) < 3:
    raise ValueError(f"{fn}: pred must have rank >= 3 ([..., F, H, W]: a sequence of F frames), "
                     f"got shape {shape}")
  _check_images(fn, pred, target, None)
  if shape[-3] < 2:
    raise ValueError(f"{fn}: a sequence needs at least 2 frames (axis -3 of [..., F, H, W]) to "
                     f"score a change between consecutive frames, got F = {shape[-3]}")
  if not isinstance(pooled, (bool, np.bool_)):
    raise ValueError(f"{fn}: pooled must be True or False, got {pooled!r}")


def _change_error(pred, target):
  """``e_t = (pred_t - pred_{t-1}) - (target_t - target_{t-1})``: ``[..., F, H, W] -> [..., F-1, H, W]``."""
  return (pred[..., 1:, :, :] - pred[..., :-1, :, :]) - (target[..., 1:, :, :] - target[..., :-1, :, :])


@functools.partial(jax.jit, static_argnames=("pooled",))
def _temporal_mse(pred, target, *, pooled):
  mse = jnp.mean(jnp.square(_change_error(pred, target)), axis=(-2, -1))     # [..., F-1]
  return jnp.mean(mse, axis=-1) if pooled else mse        # every pair has H * W pixels


@functools.partial(jax.jit, static_argnames=("pooled",))
def _temporal_rmse(pred, target, *, pooled):
  return _sqrt_guarded(_temporal_mse(pred, target, pooled=pooled))


@functools.partial(jax.jit, static_argnames=("pooled",))
def _temporal_psnr(pred, target, data_range, *, pooled):
  range_sq = jnp.square(data_range)
  mse = _temporal_mse(pred, target, pooled=pooled)
  return 10.0 * jnp.log10(range_sq / jnp.maximum(mse, range_sq * _PSNR_MSE_FLOOR))


@functools.partial(jax.jit, static_argnames=("pooled",))
def _temporal_rmse_object(pred, target, *, pooled):
  axes = (-2, -1)
  truth = _true_surface(target)
  both = truth[..., 1:, :, :] & truth[..., :-1, :, :]                          # [..., F-1, H, W]
  sq = jnp.sum(jnp.where(both, jnp.square(_change_error(pred, target)), 0), axis=axes)
  count = jnp.sum(both, axis=axes, dtype=pred.dtype)
  # NaN > 0 is false (a NaN pixel would drop out of the object): flag pairs that hold one.
  nan_frame = jnp.any(jnp.isnan(pred) | jnp.isnan(target), axis=axes)         # [..., F]
  has_nan = nan_frame[..., 1:] | nan_frame[..., :-1]
  if pooled:
    sq, count, has_nan = jnp.sum(sq, axis=-1), jnp.sum(count, axis=-1), jnp.any(has_nan, axis=-1)
  mse = jnp.where((count > 0) & ~has_nan, sq / jnp.maximum(count, 1), jnp.nan)
  return _sqrt_guarded(mse)


def temporal_rmse(pred, target, *, pooled: bool = False):
  """RMSE of the change between consecutive frames against the true change (docs/evaluation.md).

  ``sqrt(mean(e_t**2))`` over ``H, W`` with ``e_t = (pred_t - pred_{t-1}) -
  (target_t - target_{t-1})``; the units of the inputs.

  Args:
    pred: ``[..., F, H, W]`` reconstructed sequence (frames on axis -3,
      consecutive in time, ``F >= 2``), e.g. intensities in ``[0, 1]``.
    target: ``[..., F, H, W]`` ground truth, same shape and units.
    pooled: ``False``: one value per consecutive pair; ``True``: one per
      sequence, the root of the mean square over every pair and pixel.

  Returns:
    ``[..., F - 1]`` (``[...]`` pooled) float32, >= 0; 0 for a reconstruction
    that is the truth plus a constant over time. NaN for a pair holding a
    NaN (traced input).

  Raises:
    ValueError: rank < 3, ``F < 2``, shapes differ, NaN in a concrete input,
      ``pooled`` not a bool.
  """
  _check_sequences("temporal_rmse", pred, target, pooled)
  pred, target, _, _ = _prepare(pred, target, None)
  return _temporal_rmse(pred, target, pooled=bool(pooled))


def temporal_psnr(pred, target, *, data_range=1.0, pooled: bool = False):
  """PSNR (dB) of the change between consecutive frames against the true change.

  ``10 * log10(data_range**2 / max(MSE_t, data_range**2 * 1e-10))``, ``MSE_t
  = mean(e_t**2)`` (:func:`temporal_rmse` squared): the peak is the images'
  data range, as in :func:`psnr` (docs/evaluation.md, "Temporal consistency"),
  capped at :data:`PSNR_CAP_DB`.

  Args:
    pred: ``[..., F, H, W]`` reconstructed sequence, ``F >= 2``.
    target: ``[..., F, H, W]`` ground truth, same shape.
    data_range: max - min of the possible *image* values (1 for intensities
      in ``[0, 1]``); a positive scalar or an array broadcastable to the output.
    pooled: as :func:`temporal_rmse`.

  Returns:
    ``[..., F - 1]`` (``[...]`` pooled) float32, dB, at most ``PSNR_CAP_DB``.

  Raises:
    ValueError: as :func:`temporal_rmse`, and ``data_range`` not finite and > 0.
  """
  _check_sequences("temporal_psnr", pred, target, pooled)
  _check_scalar("temporal_psnr", "data_range", data_range, allow_zero=False)
  pred, target, _, dtype = _prepare(pred, target, None)
  return _temporal_psnr(pred, target, jnp.asarray(data_range, dtype), pooled=bool(pooled))


def temporal_rmse_object(pred_depth, target_depth, *, pooled: bool = False):
  """Depth RMSE (metres) of the change between consecutive frames, over the objects.

  ``sqrt(mean(e_t**2))`` over the pixels that are true surface (ground-truth
  depth > 0) in both frames ``t - 1`` and ``t`` (docs/evaluation.md,
  "Temporal consistency").

  Args:
    pred_depth: ``[..., F, H, W]`` reconstructed depth maps, metres, ``F >= 2``.
    target_depth: ``[..., F, H, W]`` true depth maps, metres, 0 at background.
    pooled: ``False``: one value per consecutive pair; ``True``: one per
      sequence, the mean square pooling every pair's object pixels.

  Returns:
    ``[..., F - 1]`` (``[...]`` pooled) float32, metres; NaN for a pair with no
    pixel that is surface in both frames (pooled: a sequence with none in any
    pair) and for a pair holding a NaN (traced input).

  Raises:
    ValueError: as :func:`temporal_rmse`.
  """
  _check_sequences("temporal_rmse_object", pred_depth, target_depth, pooled)
  pred, target, _, _ = _prepare(pred_depth, target_depth, None)
  return _temporal_rmse_object(pred, target, pooled=bool(pooled))
