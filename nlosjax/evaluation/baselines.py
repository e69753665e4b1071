"""Classic baselines on under-scanned input, and their settings chosen on the validation split.

The paper's protocol: a classic method cannot read an under-scanned grid, so
the ``h x w`` input is interpolated bilinearly to the full ``H x W`` grid
(:func:`upsample_scan`) and reconstructed there; intensity and depth come
from :func:`nlosjax.physics.intensity_depth` (max over depth, normalised; the
depth of the maximum where the intensity reaches the surface ``threshold``).

Every setting a classic method has is chosen on the **validation** split
(:func:`tune`), never on the test split, from the small grid
:func:`option_grid` (FBP falloff; LCT Wiener ``snr`` x falloff; phasor and
RSD virtual wavelength ``sampling_coeff``; f-k has none) and the surface
thresholds :data:`THRESHOLDS`:

* the reconstruction option with the highest mean validation intensity PSNR
  wins (the threshold does not change the intensity image);
* then, on that option's volumes, the threshold with the highest mean
  validation surface F1 (:func:`nlosjax.metrics.surface_scores`: recall and
  precision of "reconstructed as surface", the one rule every method is
  scored by).

Ties keep the earlier grid entry. ``tune`` returns every grid row's scores
too, so a report can show what the choice was made from.

CSA (:mod:`nlosjax.physics.methods.csa`) is no classic method in this sense: it reads the
sparse scan itself (:func:`csa_volume`), costs seconds a frame, and is chosen by the same rule
from :data:`CSA_GRID` on :data:`CSA_VAL_FRAMES` validation frames spread over the sequences
(:func:`tune_csa`, :func:`spread_frames`).

Operator variant: the tables' classic rows use ``variant="refined"`` for
FBP, LCT, f-k and phasor (:data:`TABLE_VARIANT`; the setting every table was
tuned and measured with), where the library default is the public algorithm
(``variant="public"``, see :mod:`nlosjax.physics.reconstruct`). An explicit
``variant`` in the options wins.
"""

from __future__ import annotations

import itertools
from typing import Callable

import jax.numpy as jnp
import numpy as np

# The model's interpolation (sample i at stride // 2 + stride * i, constant beyond the sampled span):
# the classic methods read the sparse scan as the networks' skip path does.
from nlosjax.models.blocks import interpolation_matrix
from nlosjax.physics.reconstruct import METHODS as CLASSIC_METHODS  # one source: the five methods

__all__ = ["CLASSIC_METHODS", "THRESHOLDS", "DEFAULT_THRESHOLD", "interpolation_matrix",
           "upsample_scan", "default_options", "option_grid", "classic_volume",
           "classic_images", "tune", "CSA_GRID", "CSA_VAL_FRAMES", "spread_frames", "csa_volume",
           "tune_csa"]

#: Surface thresholds (fraction of the image's peak intensity) tried on validation.
THRESHOLDS = (0.05, 0.1, 0.2, 0.3, 0.5)
#: :func:`nlosjax.physics.intensity_depth`'s default, used where nothing was tuned.
DEFAULT_THRESHOLD = 0.1
#: Operator variant of the methods that have one, in every table (see the module docstring).
TABLE_VARIANT = {"fbp": "refined", "lct": "refined", "fk": "refined", "phasor": "refined"}
#: CSA's settings tried on validation: l1 weight (share of max(A^T b); >= 1 empties the
#: volume) x falloff. 0.7 and 0.9 joined when 0.5, the old edge, won on the `tenth` budget.
CSA_GRID = tuple({"tau_rel": t, "falloff": f} for f in ("diffuse", "retroreflective")
                 for t in (0.03, 0.1, 0.3, 0.5, 0.7, 0.9))
#: Validation frames CSA is chosen on (it costs seconds a frame).
CSA_VAL_FRAMES = 16


def upsample_scan(transient, grid: tuple[int, int], stride: int):
  """``[..., T, h, w] -> [..., T, H, W]`` bilinear interpolation onto the full scan grid (paper protocol)."""
  my = jnp.asarray(interpolation_matrix(grid[0], stride), jnp.float32)
  mx = jnp.asarray(interpolation_matrix(grid[1], stride), jnp.float32)
  if transient.shape[-2:] != (my.shape[1], mx.shape[1]):
    raise ValueError(f"under-scanned grid {transient.shape[-2:]} does not match grid {grid} "
                     f"at stride {stride} ({my.shape[1]}, {mx.shape[1]})")
  return jnp.einsum("Hh,...thw,Ww->...tHW", my, jnp.asarray(transient, jnp.float32), mx)


def default_options(method: str, setup) -> dict:
  """Options of a classic method on ``setup`` before tuning: the defaults, with a resolved phasor wavelet.

  Phasor and RSD get ``sampling_coeff`` from
  :func:`~nlosjax.physics.wavelet.resolved_sampling_coeff` where their default
  virtual wavelength (4 scan spacings) is under 3 time bins (the ``real``
  preset); elsewhere (``cpu``, ``paper``, the measured scans) ``{}``.
  """
  from nlosjax.physics.wavelet import resolved_sampling_coeff
  _check_method(method)
  if method not in ("phasor", "rsd"):
    return {}
  coeff = resolved_sampling_coeff(setup)
  return {} if coeff <= 2.0 else {"sampling_coeff": coeff}


def option_grid(method: str, setup) -> list[dict]:
  """The reconstruction options :func:`tune` tries for ``method`` (first entry: :func:`default_options`)."""
  _check_method(method)
  if method == "fbp":
    return [{"falloff": f} for f in ("diffuse", "retroreflective")]
  if method == "lct":
    return [{"snr": s, "falloff": f}
            for f, s in itertools.product(("diffuse", "retroreflective"), (0.1, 0.01, 1.0, 10.0))]
  if method in ("phasor", "rsd"):
    base = float(default_options(method, setup).get("sampling_coeff", 2.0))
    return [{"sampling_coeff": round(base * k, 6)} for k in (1.0, 1.5, 2.0, 3.0)]
  return [{}]


def _check_method(method):
  if method not in CLASSIC_METHODS:
    raise ValueError(f"classic method must be one of {CLASSIC_METHODS}, got {method!r}")


def classic_volume(measurement, setup, stride: int, method: str, options: dict | None = None):
  """``[N, T, h, w]`` counts -> ``[N, Z, H, W]`` albedo volume of a classic method (interpolated input).

  f-k's volume (albedo squared) is square-rooted so every method returns albedo.
  """
  from nlosjax.physics import reconstruct
  _check_method(method)
  opts = default_options(method, setup) if options is None else dict(options)
  if method in TABLE_VARIANT:
    opts.setdefault("variant", TABLE_VARIANT[method])
  vol = reconstruct(upsample_scan(measurement, setup.grid, stride), setup, method, **opts)
  return jnp.sqrt(vol) if method == "fk" else vol


def classic_images(measurement, setup, stride: int, method: str, options: dict | None = None,
                   threshold: float = DEFAULT_THRESHOLD) -> tuple[np.ndarray, np.ndarray]:
  """Intensity and depth of a classic method on under-scanned input.

  Args:
    measurement: ``[N, T, h, w]`` counts of the frames to reconstruct.
    setup: the full-grid Setup.
    stride: the under-scan stride (the input is interpolated to the full grid).
    method: one of :data:`CLASSIC_METHODS`.
    options: reconstruction options (default :func:`default_options`).
    threshold: surface threshold of :func:`nlosjax.physics.intensity_depth`.
  Returns:
    ``(intensity [N, H, W] in [0, 1], depth [N, H, W] metres)`` as NumPy.
  """
  from nlosjax.physics import intensity_depth
  vol = classic_volume(measurement, setup, stride, method, options)
  inten, depth = intensity_depth(vol, setup, threshold=threshold)
  return np.asarray(inten), np.asarray(depth)


def _batched_volumes(measurement, setup, stride, method, options, batch_size):
  return [classic_volume(measurement[s:s + batch_size], setup, stride, method, options)
          for s in range(0, len(measurement), batch_size)]


def tune(measurement, gt_intensity, gt_depth, setup, stride: int, *,
         methods=CLASSIC_METHODS, thresholds=THRESHOLDS, batch_size: int = 8,
         log: Callable[[str], None] = print) -> dict:
  """Each classic method's best setting on validation frames (rules in the module docstring).

  Args:
    measurement: ``[N, T, h, w]`` under-scanned counts of the validation frames.
    gt_intensity, gt_depth: ``[N, H, W]`` their ground truth.
    setup, stride: the full-grid Setup and the under-scan stride.
    methods: classic methods to tune.
    thresholds: surface thresholds to try.
    batch_size: frames per reconstruction call.
  Returns:
    ``method -> {"options": dict, "threshold": float, "psnr": float, "f1": float,
    "grid": [{"options", "psnr", "f1_by_threshold"}, ...]}`` (validation means;
    options that a method refuses on this Setup are left out of ``grid``).
  """
  from nlosjax import metrics
  from nlosjax.physics import intensity_depth
  gt_i = np.asarray(gt_intensity)
  gt_d = np.asarray(gt_depth)
  out = {}
  for method in methods:
    rows = []
    best = None
    for options in option_grid(method, setup):
      try:
        vols = _batched_volumes(measurement, setup, stride, method, options, batch_size)
      except ValueError as e:        # e.g. a wavelength the Setup cannot carry
        log(f"[tune] {method} {options}: skipped ({e})")
        continue
      inten = np.concatenate([np.asarray(intensity_depth(v, setup)[0]) for v in vols])
      psnr = float(np.mean(np.asarray(metrics.psnr(inten, gt_i))))
      f1 = {}
      for th in thresholds:
        depth = np.concatenate([np.asarray(intensity_depth(v, setup, threshold=th)[1]) for v in vols])
        f1[float(th)] = float(np.nanmean(np.asarray(metrics.surface_scores(depth, gt_d)["f1"])))
      rows.append({"options": options, "psnr": psnr, "f1_by_threshold": f1})
      if best is None or psnr > best["psnr"]:
        best = rows[-1]
    if best is None:
      raise ValueError(f"no option of {method!r} works on {setup}")
    f1 = best["f1_by_threshold"]
    th = max(f1, key=lambda t: (f1[t], -list(f1).index(t)))
    out[method] = {"options": best["options"], "threshold": th, "psnr": best["psnr"],
                   "f1": f1[th], "grid": rows}
    log(f"[tune] {method}: {best['options'] or 'no options'}, threshold {th} "
        f"(validation intensity PSNR {best['psnr']:.2f} dB, surface F1 {f1[th]:.3f})")
  return out


def spread_frames(n: int, k: int) -> np.ndarray:
  """Indices of ``min(k, n)`` of ``n`` frames spread evenly over them (first and last included)."""
  if n < 1 or k < 1:
    raise ValueError(f"need n >= 1 frames and k >= 1 picks, got n={n}, k={k}")
  return np.unique(np.linspace(0, n - 1, min(k, n)).round().astype(int))


def csa_volume(measurement, setup, stride: int, options: dict):
  """``[N, T, h, w]`` under-scanned counts -> ``[N, Z, H, W]`` CSA volume of the sparse scan.

  The counts go to their scan points of the full grid
  (:func:`nlosjax.physics.methods.csa.sparse_on_grid`); CSA reads only those (its mask).
  """
  from nlosjax.physics.methods import csa
  H, W = setup.grid
  return csa.csa(csa.sparse_on_grid(jnp.asarray(measurement, jnp.float32), (H, W), stride), setup,
                 mask=csa.interval_mask(H, W, stride), **options)


def tune_csa(measurement, gt_intensity, gt_depth, setup, stride: int, *, grid=CSA_GRID,
             thresholds=THRESHOLDS, batch_size: int = 8, log: Callable[[str], None] = print) -> dict:
  """CSA's best setting on validation frames, by :func:`tune`'s rule.

  Args:
    measurement: ``[N, T, h, w]`` under-scanned counts (a few frames: :func:`spread_frames`).
    gt_intensity, gt_depth: ``[N, H, W]`` their ground truth.
    grid: option dicts of :func:`csa_volume` to try; thresholds: surface thresholds to try.
  Returns:
    ``{"options", "threshold", "psnr", "f1", "grid": [{"options", "psnr"}, ...]}`` (validation
    means): the options with the best mean intensity PSNR (ties: the earlier), at them the
    threshold with the best mean surface F1.
  """
  from nlosjax import metrics
  from nlosjax.physics import intensity_depth
  gt_i = np.asarray(gt_intensity)
  rows, best, best_vols = [], None, None
  for options in grid:
    vols = [np.asarray(csa_volume(measurement[s:s + batch_size], setup, stride, options))
            for s in range(0, len(measurement), batch_size)]
    inten = np.concatenate([np.asarray(intensity_depth(v, setup)[0]) for v in vols])
    psnr = float(np.mean(np.asarray(metrics.psnr(inten, gt_i))))
    rows.append({"options": dict(options), "psnr": psnr})
    log(f"[tune] csa {options}: validation intensity PSNR {psnr:.2f} dB")
    if best is None or psnr > best["psnr"]:
      best, best_vols = rows[-1], vols
  f1 = {}
  for th in thresholds:
    depth = np.concatenate([np.asarray(intensity_depth(v, setup, threshold=th)[1]) for v in best_vols])
    f1[float(th)] = float(np.nanmean(np.asarray(metrics.surface_scores(depth, np.asarray(gt_depth))["f1"])))
  th = max(f1, key=lambda t: (f1[t], -list(f1).index(t)))
  log(f"[tune] csa: {best['options']}, threshold {th} "
      f"(validation intensity PSNR {best['psnr']:.2f} dB, surface F1 {f1[th]:.3f})")
  return {"options": best["options"], "threshold": th, "psnr": best["psnr"], "f1": f1[th], "grid": rows}
