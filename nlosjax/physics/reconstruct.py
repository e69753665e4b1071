"""Confocal NLOS reconstructions: the classic FBP, LCT, f-k, phasor fields, RSD, and the iterative CSA.

Every method maps a transient ``[..., T, H, W]`` (counts, non-negative) to a
non-negative volume ``[..., Z, H, W]`` on the Setup's depth grid (``Z`` =
``setup.num_depth_bins``; depth bin ``k`` at ``z = k c dt / 2``). Every method
honours ``setup.depth_range``: it reads only the time bins that can hold
returns from that range (``setup.time_bins``) and computes only its depth
bins, so cost falls with the range. All are jit-compiled, batched over the
leading axes with ``vmap``, and build their operators once per Setup.

``lct``, ``fbp`` and ``phasor`` take ``variant`` (``fk`` too, for its lateral
frequencies: its docstring). ``"public"`` (the default)
is the public algorithm's operators: O'Toole's resampling matrix and
one-voxel cone PSF on the full ``(2T, 2H, 2W)`` circular box (every time bin
read; a depth range only crops), so a Wiener ``snr`` carries over from the
public code and gives its image. ``"refined"`` is ours: a cone averaged over
each voxel's footprint on the true scan spacing, linear convolution, gating,
``oversample`` (see ``operators``); its measured benefit on point scatterers
and measured scans is in ``benchmarks/results/physics.md``.

Where each differs from the public reference code (nlos-fk, O'Toole's LCT,
nlos3d, LFE/USM):

* ``fbp``: the public code filters the backprojection with ``+LoG``, which is
  negative on objects, and clamps -- keeping only halos. We use ``-LoG``
  (5x5x5, sigma = 1 voxel, replicate padding) and do not normalise by the maximum.
* ``lct``: none with ``variant="public"``; see above for ``"refined"``.
* ``fk``: the Stolt interpolation is done on physical frequencies (any grid
  aspect and spacing), from a one-sided (``rfft``) temporal spectrum; the
  output is ``albedo^2`` like the public code. ``variant="public"`` (default)
  uses the public code's implied scan spacing ``wall_size / N``;
  ``"refined"`` the Setup's ``wall_size / (N - 1)``.
* ``phasor``: none with ``variant="public"`` (MATLAB ``conv(..., 'same')``
  with the public wavelet, even length allowed). ``"refined"``: the wavelet is
  odd-length and centred (no +-1-bin shift), and time is resampled to ``v`` by
  plain bin averaging; the public ``mtx`` also weights by ``1/t``, which tilts
  the long wavelet envelope (139 bins on a 16 x 16, 1 m, 32 ps scan) and pulls
  peaks 3-6 bins toward the wall at 0.5 m.
* ``rsd``: the confocal adaptation of Liu et al. 2019 (round-trip wavenumber
  ``2 omega / c``, no source-phase term), propagated with the exact
  angular-spectrum transfer function of Rayleigh-Sommerfeld diffraction
  rather than a sampled ``exp(ikd)/d`` kernel (no ``1/d`` singularity at
  ``z = 0``, no kernel FFTs); frequencies are the DFT frequencies of the full
  window whose wavelet spectrum exceeds ``ratio``. The sum over frequencies
  at every depth plane is a type-1 non-uniform FFT (``O(K + Z log Z)`` per
  lateral frequency instead of ``O(K Z)``; float32-exact, the direct sum
  stays available as ``depth_sum="direct"``).

Each method lives in its own module of :mod:`nlosjax.physics.methods`
(``lct.py``, ``fbp.py``, ``fk.py``, ``phasor.py``, ``rsd.py``, ``csa.py``, each with its
private helpers; ``fbp`` and ``phasor`` build on ``lct``'s cached operators).
This module holds the :func:`reconstruct` dispatch and re-exports the six
functions and the helpers tests and benchmarks import from here
(``neg_log_filter``, ``wavelet_matrix``, ``_rsd_plan``, ...: ``x as x``
imports); "the module docstring" in the methods' docstrings is this one.
"""

from __future__ import annotations

import jax

from nlosjax.physics.depth_range import auto_depth_range
from nlosjax.physics.methods.csa import csa
from nlosjax.physics.methods.fbp import _neg_log_kernel as _neg_log_kernel
from nlosjax.physics.methods.fbp import fbp
from nlosjax.physics.methods.fbp import neg_log_filter as neg_log_filter
from nlosjax.physics.methods.fk import fk
from nlosjax.physics.methods.lct import lct
from nlosjax.physics.methods.phasor import phasor
from nlosjax.physics.methods.phasor import wavelet_matrix as wavelet_matrix
from nlosjax.physics.methods.rsd import _rsd_operators as _rsd_operators
from nlosjax.physics.methods.rsd import _rsd_plan as _rsd_plan
from nlosjax.physics.methods.rsd import _rsd_window as _rsd_window
from nlosjax.physics.methods.rsd import rsd
from nlosjax.physics.setup import Setup

METHODS = ("fbp", "lct", "fk", "phasor", "rsd")
#: Iterative methods: a solver with a prior, for under-scanned captures (``mask=``).
ITERATIVE_METHODS = ("csa",)


# ------------------------------------------------------------------ dispatch
_FUNCTIONS = {"fbp": fbp, "lct": lct, "fk": fk, "phasor": phasor, "rsd": rsd, "csa": csa}


def reconstruct(transient, setup: Setup, method: str, *, depth_range=None, **options) -> jax.Array:
  """Reconstruct a hidden volume with one of the classic methods or CSA.

  Args:
    transient: ``[..., T, H, W]`` counts >= 0 (t = 0 at the wall).
    setup: the capture; its ``depth_range`` gates time and crops the volume.
    method: ``"fbp"``, ``"lct"``, ``"fk"``, ``"phasor"``, ``"rsd"`` or ``"csa"``
      (:func:`nlosjax.physics.methods.csa.csa`: iterative, takes the scan ``mask``
      of an under-scanned capture).
    depth_range: ``None`` (the Setup's), ``(z_min, z_max)`` metres, or
      ``"auto"``: estimated from the capture
      (:func:`nlosjax.physics.depth_range.auto_depth_range`; the volume's depth
      bins are that Setup's ``depth_bins``; concrete input only).
    **options: passed to the method (e.g. ``snr``, ``falloff`` for ``lct``).
  Returns:
    ``[..., Z, H, W]`` float32 volume, >= 0 (``fk``: albedo squared).
  Raises:
    ValueError: unknown method or option, bad shapes or values.
  """
  if method not in _FUNCTIONS:
    raise ValueError(f"unknown method {method!r}; choose one of {METHODS + ITERATIVE_METHODS}")
  if isinstance(depth_range, str):
    if depth_range != "auto":
      raise ValueError(f"depth_range must be None, (z_min, z_max) or 'auto', got {depth_range!r}")
    setup = auto_depth_range(transient, setup)
  elif depth_range is not None:
    setup = setup.ungated().with_depth_range(*depth_range)
  fn = _FUNCTIONS[method]
  try:
    return fn(transient, setup, **options)
  except TypeError as e:
    if "unexpected keyword" in str(e):
      raise ValueError(f"method {method!r} does not take option(s) {sorted(options)}: {e}") from None
    raise
