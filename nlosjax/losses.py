"""Training losses of ST-Mamba (paper Eq. 5-6) and the predecessor's regularisers.

``L = L_m + beta L_v + gamma L_r`` with

* ``L_m = L_pf + alpha1 L_t`` (measurement recovery),
* ``L_v = L_int + alpha2 L_dep`` (volume reconstruction; optionally ``+ w_obj L_obj``,
  the intensity error over the true surface pixels, which the paper does not have; and
  with ``balance > 0``, ``L_int`` and ``L_dep`` weigh the object pixels apart from the
  background, :func:`balanced_rmse_loss`, which the paper does not do either),
* ``L_r = L_ls + alpha3 L_tv`` (regularisation, as USM).

Every term is computed per sample and averaged over the batch, so its weight
does not depend on the batch size (USM summed TV over the batch). The paper's
``||.||_2`` terms are root-mean-square errors over a sample's elements, with a
guarded square root: ``sqrt(mean + eps)``, whose gradient is 0, not infinite,
at zero error. A term whose weight is 0 is not computed.

Shapes: transient ``[B, T, H, W]``, volume ``[B, Z, H, W]``, intensity and
depth ``[B, H, W]``. Units are those of the inputs (the trainer feeds
normalised transients, intensities in [0, 1] and depths in metres).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from nlosjax.physics.wavelet import Wavelet, convolve_time

SQRT_EPS = 1e-12


def _per_sample_rms(diff: jax.Array) -> jax.Array:
  """``[B]`` guarded root-mean-square of ``|diff|`` over all non-batch axes."""
  sq = jnp.real(diff * jnp.conj(diff)) if jnp.iscomplexobj(diff) else diff * diff
  mean = jnp.mean(sq.reshape(sq.shape[0], -1).astype(jnp.float32), axis=1)
  return jnp.sqrt(mean + SQRT_EPS)


def rmse_loss(pred: jax.Array, target: jax.Array) -> jax.Array:
  """Batch mean of per-sample RMSE: ``mean_b sqrt(mean_i (pred - target)^2 + eps)``.

  Args:
    pred, target: ``[B, ...]`` of one shape.
  Returns:
    scalar float32.
  """
  if pred.shape != target.shape:
    raise ValueError(f"pred {pred.shape} and target {target.shape} differ in shape")
  return jnp.mean(_per_sample_rms(pred - target))


def transient_loss(pred: jax.Array, target: jax.Array) -> jax.Array:
  """``L_t = ||tau - tau_gt||_2`` (per-sample RMSE, batch mean); ``[B, T, H, W]`` each."""
  return rmse_loss(pred, target)


def phasor_field_loss(pred: jax.Array, target: jax.Array, wavelet: Wavelet) -> jax.Array:
  """``L_pf = ||tau * P - tau_gt * P||_2``: transients compared in the phasor field.

  Both are convolved along time with the complex illumination wavelet ``P(t)``
  (:func:`nlosjax.physics.illumination_wavelet`); by linearity this is the
  RMS modulus of ``(tau - tau_gt) * P``, which weights the band the phasor
  reconstruction uses and ignores the rest (DC background, bin noise).

  Args:
    pred, target: ``[B, T, H, W]``.
    wavelet: the illumination wavelet of the model's Setup.
  Returns:
    scalar float32.
  """
  if pred.shape != target.shape:
    raise ValueError(f"pred {pred.shape} and target {target.shape} differ in shape")
  field = convolve_time((pred - target).astype(jnp.float32), wavelet, axis=1)
  return jnp.mean(_per_sample_rms(field))


def intensity_loss(pred: jax.Array, target: jax.Array) -> jax.Array:
  """``L_int = ||I - I_gt||_2``; ``[B, H, W]`` each."""
  return rmse_loss(pred, target)


def object_intensity_loss(pred: jax.Array, target: jax.Array, target_depth: jax.Array,
                          background_depth: float = 0.0) -> jax.Array:
  """``L_obj = ||I - I_gt||_2`` over the true surface pixels only; not in the paper.

  The whole-image ``L_int`` is dominated by background pixels, so a model
  that leaves a dim or far object dark pays little for it. This term is the
  per-sample RMSE over the pixels whose target depth is not
  ``background_depth`` (a sample with none contributes 0), averaged over the
  batch.

  Args:
    pred, target: ``[B, H, W]`` intensities.
    target_depth: ``[B, H, W]`` metres; ``background_depth`` where empty.
    background_depth: the target's empty-pixel depth (the dataset's, 0 m).
  Returns:
    scalar float32.
  """
  if not pred.shape == target.shape == target_depth.shape:
    raise ValueError(f"pred {pred.shape}, target {target.shape} and target_depth "
                     f"{target_depth.shape} differ in shape")
  mask = (target_depth != background_depth).astype(jnp.float32)
  d = (pred - target).astype(jnp.float32)
  b = pred.shape[0]
  num = jnp.sum((mask * d * d).reshape(b, -1), axis=1)
  count = jnp.sum(mask.reshape(b, -1), axis=1)
  return jnp.mean(jnp.sqrt(num / jnp.maximum(count, 1.0) + SQRT_EPS))


def balanced_rmse_loss(pred: jax.Array, target: jax.Array, target_depth: jax.Array, balance: float,
                       background_depth: float = 0.0) -> jax.Array:
  """Per-sample RMSE with the object pixels weighed apart from the background; batch mean.

  ``sqrt((1 - b) MSE + b (MSE_obj + MSE_bg) / 2 + eps)`` with ``b = balance``: ``MSE`` over
  every pixel (``b = 0``: :func:`rmse_loss`, the paper's ``||.||_2``), ``MSE_obj`` and
  ``MSE_bg`` each over its own pixels (the object pixels: ``target_depth != background_depth``;
  a sample with only one kind counts that kind's MSE for both). At ``b = 1`` object and
  background pixels weigh half each whatever their counts (the objects of the ``cpu`` preset
  cover about a twelfth of an image): the loss form of
  :func:`nlosjax.metrics.psnr_balanced`.

  Args:
    pred, target: ``[B, H, W]``.
    target_depth: ``[B, H, W]`` metres; ``background_depth`` where empty.
    balance: in ``[0, 1]``.
  Returns:
    scalar float32.
  """
  if not pred.shape == target.shape == target_depth.shape:
    raise ValueError(f"pred {pred.shape}, target {target.shape} and target_depth "
                     f"{target_depth.shape} differ in shape")
  if not 0.0 <= balance <= 1.0:
    raise ValueError(f"balance must be in [0, 1], got {balance!r}")
  b = pred.shape[0]
  obj = (target_depth != background_depth).reshape(b, -1).astype(jnp.float32)
  sq = jnp.square((pred - target).astype(jnp.float32)).reshape(b, -1)
  n_obj, n_bg = jnp.sum(obj, axis=1), jnp.sum(1.0 - obj, axis=1)
  mse_obj = jnp.sum(obj * sq, axis=1) / jnp.maximum(n_obj, 1.0)
  mse_bg = jnp.sum((1.0 - obj) * sq, axis=1) / jnp.maximum(n_bg, 1.0)
  halves = jnp.where((n_obj > 0) & (n_bg > 0), 0.5 * (mse_obj + mse_bg), jnp.where(n_obj > 0, mse_obj, mse_bg))
  return jnp.mean(jnp.sqrt((1.0 - balance) * jnp.mean(sq, axis=1) + balance * halves + SQRT_EPS))


def depth_loss(pred: jax.Array, target: jax.Array) -> jax.Array:
  """``L_dep = ||D - D_gt||_2`` in metres; ``[B, H, W]`` each."""
  return rmse_loss(pred, target)


# USM's local-similarity blur: 3 x 3 Gaussian, sigma 1.5, normalised.
_LS_TAPS = np.exp(-np.arange(-1, 2) ** 2 / (2 * 1.5 ** 2))
_LS_TAPS = tuple((_LS_TAPS / _LS_TAPS.sum()).tolist())


def _blur3(volume: jax.Array) -> jax.Array:
  """3 x 3 Gaussian blur over the last two axes, replicate padding."""
  p = jnp.pad(volume, [(0, 0)] * (volume.ndim - 2) + [(1, 1), (1, 1)], mode="edge")
  h, w = volume.shape[-2:]
  rows = sum(c * p[..., i:i + h, :] for i, c in enumerate(_LS_TAPS))
  return sum(c * rows[..., :, j:j + w] for j, c in enumerate(_LS_TAPS))


def local_similarity_loss(volume: jax.Array) -> jax.Array:
  """``L_ls = ||V - G * V||_2``: USM's local similarity.

  ``G`` is a 3 x 3 Gaussian (sigma 1.5) applied to each depth slice over
  (H, W) with replicate padding: the term penalises voxels unlike their
  lateral neighbours. A feature volume ``[B, Z, H, W, C]`` (USM's ``V``)
  gets the sum over its channels of each channel's term, as USM.

  Args:
    volume: ``[B, Z, H, W]`` or ``[B, Z, H, W, C]``.
  Returns:
    scalar float32.
  """
  volume = volume.astype(jnp.float32)
  if volume.ndim == 5:
    return sum(local_similarity_loss(volume[..., c]) for c in range(volume.shape[-1]))
  return jnp.mean(_per_sample_rms(volume - _blur3(volume)))


def tv_loss(volume: jax.Array) -> jax.Array:
  """``L_tv``: anisotropic 3D total variation, summed per sample, batch mean.

  ``sum |V[z+1] - V[z]| + |V[h+1] - V[h]| + |V[w+1] - V[w]|`` over a sample
  (a sum, as USM, so the paper's weight ``gamma alpha3 = 1e-6`` keeps its
  meaning), averaged over the batch. ``|x|`` is smoothed as
  ``sqrt(x^2 + eps) - sqrt(eps)`` so its gradient is defined at 0.

  Args:
    volume: ``[B, Z, H, W]``, or ``[B, Z, H, W, C]`` (a feature volume: the
      sum runs over its channels too, never across them).
  Returns:
    scalar float32.
  """
  volume = volume.astype(jnp.float32)
  eps = SQRT_EPS
  total = 0.0
  axes = tuple(range(1, volume.ndim))
  for axis in (1, 2, 3):
    d = jnp.diff(volume, axis=axis)
    total = total + jnp.sum(jnp.sqrt(d * d + eps) - np.sqrt(eps), axis=axes)
  return jnp.mean(total)


@dataclasses.dataclass(frozen=True)
class LossWeights:
  """Weights of ``L = L_m + beta L_v + gamma L_r`` (defaults: the paper's Sec. 5.1).

  A weight of 0 switches its term off (it is then not computed): the loss
  ablations of the paper's Table 2. ``phasor_field`` scales ``L_pf`` inside
  ``L_m`` (1 in the paper; 0 ablates it).
  """

  phasor_field: float = 1.0
  alpha1: float = 0.5      # transient
  alpha2: float = 1.0      # depth
  alpha3: float = 0.1      # total variation
  beta: float = 1.0        # volume terms
  gamma: float = 1e-5      # regularisers
  intensity: float = 1.0   # scales L_int inside L_v (1 in the paper)
  local_similarity: float = 1.0   # scales L_ls inside L_r (1 in the paper)
  object_intensity: float = 0.0   # L_int over true surface pixels, inside L_v (not in the paper)
  balance: float = 0.0     # in [0, 1]: L_int and L_dep weigh object pixels apart (balanced_rmse_loss; 0: the paper)

  #: Weights added after checkpoints were first written, with their defaults.
  _LATER_FIELDS = {"object_intensity": 0.0, "balance": 0.0}

  def to_dict(self) -> dict:
    """The weights as a dict; a weight added later is absent at its default, so a
    checkpoint's recorded settings from before it existed still match."""
    d = dataclasses.asdict(self)
    for name, default in self._LATER_FIELDS.items():
      if d[name] == default:
        d.pop(name)
    return d

  def __post_init__(self):
    for f in dataclasses.fields(self):
      v = getattr(self, f.name)
      if not (isinstance(v, (int, float)) and np.isfinite(v) and v >= 0):
        raise ValueError(f"loss weight {f.name} must be a finite number >= 0, got {v!r}")
    if self.balance > 1:
      raise ValueError(f"loss balance must be in [0, 1], got {self.balance!r}")


def total_loss(outputs: dict, targets: dict, weights: LossWeights,
               wavelet: Wavelet | None) -> tuple[jax.Array, dict]:
  """The paper's total loss and its terms.

  Args:
    outputs: the model's ``{"transient": [B, T, H, W], "volume": [B, Z, H, W],
      "intensity": [B, H, W], "depth": [B, H, W]}``; where it also holds
      ``"feature_volume"`` ``[B, Z', H', W', C]`` (USM's refined volume), the
      regularisers act on that instead of ``"volume"``, as USM's.
    targets: ``{"transient", "intensity", "depth"}`` of the same shapes.
    weights: :class:`LossWeights`.
    wavelet: illumination wavelet for ``L_pf`` (may be None when
      ``weights.phasor_field == 0``).
  Returns:
    ``(loss, terms)``: scalar float32 and a dict of the unweighted terms
    that were computed (``pf, t, int, obj, dep, ls, tv``) plus ``m, v, r``.
  """
  w = weights
  terms = {}
  zero = jnp.zeros((), jnp.float32)
  if w.phasor_field:
    if wavelet is None:
      raise ValueError("wavelet is needed when weights.phasor_field > 0")
    terms["pf"] = phasor_field_loss(outputs["transient"], targets["transient"], wavelet)
  if w.alpha1:
    terms["t"] = transient_loss(outputs["transient"], targets["transient"])
  if w.beta and w.intensity:
    terms["int"] = (balanced_rmse_loss(outputs["intensity"], targets["intensity"], targets["depth"], w.balance)
                    if w.balance else intensity_loss(outputs["intensity"], targets["intensity"]))
  if w.beta and w.object_intensity:
    terms["obj"] = object_intensity_loss(outputs["intensity"], targets["intensity"],
                                         targets["depth"])
  if w.beta and w.alpha2:
    terms["dep"] = (balanced_rmse_loss(outputs["depth"], targets["depth"], targets["depth"], w.balance)
                    if w.balance else depth_loss(outputs["depth"], targets["depth"]))
  regularised = outputs.get("feature_volume", outputs["volume"])
  if w.gamma and w.local_similarity:
    terms["ls"] = local_similarity_loss(regularised)
  if w.gamma and w.alpha3:
    terms["tv"] = tv_loss(regularised)
  g = terms.get
  terms["m"] = w.phasor_field * g("pf", zero) + w.alpha1 * g("t", zero)
  terms["v"] = (w.intensity * g("int", zero) + w.alpha2 * g("dep", zero)
                + w.object_intensity * g("obj", zero))
  terms["r"] = w.local_similarity * g("ls", zero) + w.alpha3 * g("tv", zero)
  loss = terms["m"] + w.beta * terms["v"] + w.gamma * terms["r"]
  return loss, terms


def mmd2(x: jax.Array, y: jax.Array, bandwidths=(0.5, 1.0, 2.0, 4.0)) -> jax.Array:
  """Unbiased squared maximum mean discrepancy between two samples, Gaussian kernels summed.

  ``k(a, b) = sum_s exp(-|a - b|^2 / (2 s^2 d))`` over ``bandwidths`` ``s`` (in units of
  ``sqrt(d)``, so they suit standardised features of any dimension ``d``); the U-statistic
  ``mean_{i != j} k(x_i, x_j) + mean_{i != j} k(y_i, y_j) - 2 mean_{i, j} k(x_i, y_j)``
  (Gretton et al. 2012), 0 in expectation when both come from one distribution.

  Args:
    x: ``[n, d]``, y: ``[m, d]`` samples (n, m >= 2).
  Returns:
    scalar float32 (may be slightly negative by chance).
  """
  x = jnp.asarray(x, jnp.float32)
  y = jnp.asarray(y, jnp.float32)
  if x.ndim != 2 or y.ndim != 2 or x.shape[1] != y.shape[1] or x.shape[0] < 2 or y.shape[0] < 2:
    raise ValueError(f"x and y must be [n, d] and [m, d] with n, m >= 2, got {x.shape} and {y.shape}")
  d = x.shape[1]

  def kernel(a, b):
    sq = jnp.maximum(jnp.sum(a * a, 1)[:, None] + jnp.sum(b * b, 1)[None, :] - 2.0 * a @ b.T, 0.0)
    return sum(jnp.exp(-sq / (2.0 * s * s * d)) for s in bandwidths)

  def off_diagonal_mean(k):
    n = k.shape[0]
    return (jnp.sum(k) - jnp.trace(k)) / (n * (n - 1))

  return off_diagonal_mean(kernel(x, x)) + off_diagonal_mean(kernel(y, y)) - 2.0 * jnp.mean(kernel(x, y))
