"""Sequence simulation: :func:`simulate_sequence` renders a sequence's scene and draws its SPAD counts.

Also the rendering Setup (:func:`render_setup`), the count model
(:func:`measurement_rate`) and the compact storage of ``clean``; units and
noise model in the :mod:`nlosjax.data.dataset` docstring.
"""

from __future__ import annotations

import json
import math

import numpy as np

from nlosjax.data import scenes
from nlosjax.data.dataset.spec import DatasetSpec, sequence_name, sequence_seed
from nlosjax.physics.setup import Setup


def _log_uniform(rng, lo, hi):
  if lo == hi:
    return float(lo)
  return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def render_setup(spec: DatasetSpec) -> Setup:
  """The gated Setup used to render: the scene's depth range widened by 2 bins.

  Objects' bounding spheres lie inside ``spec.scene.depth_range``, so gating
  to it loses no albedo and renders 2-3x faster at paper scale (the
  transient keeps all ``T`` bins; see :func:`nlosjax.physics.render`).
  """
  s = spec.setup
  dz = s.depth_bin_length
  z0, z1 = spec.scene.depth_range
  return s.with_depth_range(max(0.0, z0 - 2 * dz), min(s.max_depth - dz / 2, z1 + 2 * dz))


def measurement_rate(clean, setup: Setup, *, efficiency: float, ambient: float, dark_counts: float,
                     jitter) -> np.ndarray:
  """Expected SPAD counts ``eta * (clean (*) g + ambient) + dark_counts`` per bin.

  Args:
    clean: ``[..., T, H, W]`` expected incident signal photons per bin.
    setup: the full-resolution capture.
    efficiency: detection efficiency in ``(0, 1]``.
    ambient: incident ambient photons per bin per scan point.
    dark_counts: dark counts per bin per scan point.
    jitter: ``"measured"``, a FWHM in seconds, or ``None``.
  Returns:
    ``[..., T, H, W]`` float32 (:func:`nlosjax.physics.expected_counts` with ``pulses=1``).
  """
  from nlosjax.physics.noise import expected_counts
  return np.asarray(expected_counts(clean, setup, pulses=1.0, efficiency=efficiency,
                                    ambient=ambient, dark_counts=dark_counts, jitter=jitter))


#: ``clean`` keeps this many mantissa bits (relative rounding error <= 2**-13)
#: and zeroes values below ``_CLEAN_FLOOR`` times its peak: 3x smaller files.
_CLEAN_BITS = 12
_CLEAN_FLOOR = 1e-6


def _compact(x: np.ndarray) -> np.ndarray:
  """float32 ``x`` rounded to ``_CLEAN_BITS`` mantissa bits, tiny values zeroed."""
  x = np.where(x > _CLEAN_FLOOR * float(x.max(initial=0.0)), x, 0.0).astype(np.float32)
  drop = 23 - _CLEAN_BITS
  u = x.view(np.uint32)
  u = (u + np.uint32(1 << (drop - 1))) & np.uint32((0xFFFFFFFF >> drop) << drop)
  return u.view(np.float32)


def _render_clean(spec: DatasetSpec, scene, maps, gated: Setup, fm) -> np.ndarray:
  """``[F, T, H, W]`` float32 noise-free transient of every frame (arbitrary scale).

  ``fm``: the sequence's :class:`~nlosjax.data.dataset.physics.ForwardModel`
  (``renderer="mix"``), else ``None`` (``spec.renderer`` decides).
  """
  from nlosjax.physics.forward import render
  setup = spec.setup
  F, T = spec.frames, setup.num_bins
  renderer = spec.renderer if fm is None else fm.family
  if renderer in ("transport", "points"):   # every frame in one call: objects sampled once
    from nlosjax.data import surfaces
    if fm is None:
      return surfaces.render_scene(scene, setup, retroreflective=spec.retroreflective)
    return surfaces.render_scene(scene, setup, falloff_power=fm.object_powers(len(scene.objects)),
                                 cosine_power=fm.cosine_power, occlusion=renderer == "transport")
  k0, k1 = gated.depth_bins
  clean = np.empty((F, T) + setup.grid, np.float32)
  for start in range(0, F, spec.render_batch):
    stop = min(F, start + spec.render_batch)
    vol = maps.volume(setup, slice(start, stop))
    if np.any(vol[:, :k0]) or np.any(vol[:, k1:]):  # cannot happen for valid scenes
      clean[start:stop] = np.asarray(render(vol, setup, falloff=spec.falloff))
    else:
      clean[start:stop] = np.asarray(render(vol[:, k0:k1], gated, falloff=spec.falloff))
  if fm is not None:   # r^-4 -> r^-p: every return in bin t comes from r = (t + 1/2) c dt / 2
    r = (np.arange(T) + 0.5) * setup.bin_length / 2
    clean *= (r ** (4.0 - fm.scene_falloff)).astype(np.float32)[:, None, None]
  return clean


def mixed_rate(clean, setup: Setup, fm, *, efficiency: float, ambient_total: float,
               dark_counts: float) -> np.ndarray:
  """Expected counts ``[F, T, H, W]`` under a drawn forward model (``renderer="mix"``).

  ``eta * gain * (shift(sweep(clean) (*) g) + b) + dark / T`` per bin, with ``g``
  the draw's impulse response, ``b [T]`` its ambient profile summing to
  ``ambient_total`` (photons per histogram), ``gain [H, W]`` its gain map,
  ``sweep`` its scanner sweep (:func:`~nlosjax.data.dataset.physics.sweep_smear`,
  the identity at ``sweep_length = 0``) and ``shift`` its time-zero offset
  (zero-filled); 0 in the bins that start before its gate time. ``clean`` ``[F, T, H, W]`` in incident photons per bin;
  ``dark_counts`` per histogram.
  """
  from nlosjax.data.dataset import physics
  signal = measurement_rate(clean, setup, efficiency=1.0, ambient=0.0, dark_counts=0.0,
                            jitter=physics.impulse_kernel(setup, fm)).astype(np.float64)
  if fm.sweep_length > 0:   # linear in the scan point: commutes with the per-point convolution
    signal = physics.sweep_smear(signal, fm.sweep_length, fm.sweep_serpentine)
  d = fm.time_shift
  if d:
    shifted = np.zeros_like(signal)
    if d > 0:
      shifted[:, d:] = signal[:, :-d]
    else:
      shifted[:, :d] = signal[:, -d:]
    signal = shifted
  background = physics.background_profile(setup, fm, ambient_total)[:, None, None]
  gain = physics.gain_map(setup, fm)
  rate = efficiency * gain * (signal + background) + dark_counts / setup.num_bins
  gated = int(np.ceil(fm.gate_time / setup.bin_width - 1e-9))
  rate[:, :gated] = 0.0
  return np.maximum(rate, 0.0).astype(np.float32)


def simulate_sequence(spec: DatasetSpec, split: str, index: int) -> dict:
  """Simulate one sequence (deterministic in ``spec``, ``split`` and ``index``).

  Returns:
    ``{"name", "arrays": {dataset name -> numpy array}, "attrs": {...}}``
    with the datasets and attributes of the HDF5 layout (package docstring):
    ``measurement [F, T, H, W]`` uint16/uint32, ``clean [F, T, H, W]``
    float32 (if ``spec.store_clean``), ``albedo [F, T, H, W]`` float32 (if
    ``spec.store_albedo``), ``intensity``/``depth`` ``[F, H, W]`` float32,
    ``trajectory [F, 3]`` float64.
  """
  import jax

  from nlosjax.physics.noise import add_spad_noise

  setup = spec.setup
  seed = sequence_seed(spec.seed, split, index)
  scene = scenes.make_scene(seed, spec.scene, spec.frames, setup=setup)
  rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(1,)))
  efficiency = float(rng.uniform(*spec.efficiency))
  photons = _log_uniform(rng, *spec.photons)
  ambient_total = 0.0 if spec.ambient[1] == 0 else _log_uniform(rng, *spec.ambient)
  T = setup.num_bins
  ambient, dark = ambient_total / T, spec.dark_counts / T

  maps = scenes.rasterize(scene, setup, supersample=spec.scene.supersample)
  gated = render_setup(spec)
  F = spec.frames
  fm = None if spec.physics is None else spec.physics.draw(seed, setup)
  clean = _render_clean(spec, scene, maps, gated, fm)
  albedo = None
  if spec.store_albedo:
    albedo = np.empty((F, T) + setup.grid, np.float32)
    for start in range(0, F, spec.render_batch):
      albedo[start:start + spec.render_batch] = maps.volume(setup, slice(start, start + spec.render_batch))
  energy = float(np.mean(np.sum(clean, axis=1, dtype=np.float64)))
  if not energy > 0:
    raise ValueError(f"sequence {sequence_name(split, index)} (seed {seed}) renders no signal")
  scale = photons / energy
  clean = _compact(clean * np.float32(scale))

  counts = np.empty(clean.shape, np.float32)
  if fm is not None:
    dark_total = spec.dark_counts if fm.dark_counts is None else fm.dark_counts
    dark = dark_total / T
    lam = mixed_rate(clean, setup, fm, efficiency=efficiency, ambient_total=ambient_total,
                     dark_counts=dark_total)
    for f in range(F):
      frame_rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(2, f)))
      counts[f] = frame_rng.poisson(lam[f])
  elif spec.noise_sampler == "jax":
    key = jax.random.key(seed)
    for f in range(F):
      counts[f] = np.asarray(add_spad_noise(
          jax.random.fold_in(key, f), clean[f], setup, pulses=1.0, efficiency=efficiency,
          ambient=ambient, dark_counts=dark, jitter=spec.jitter))
  else:
    for start in range(0, F, spec.render_batch):
      stop = min(F, start + spec.render_batch)
      lam = measurement_rate(clean[start:stop], setup, efficiency=efficiency, ambient=ambient,
                             dark_counts=dark, jitter=spec.jitter)
      for f in range(start, stop):
        frame_rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(2, f)))
        counts[f] = frame_rng.poisson(lam[f - start])
  peak = float(counts.max()) if counts.size else 0.0
  measurement = counts.astype(np.uint16 if peak <= np.iinfo(np.uint16).max else np.uint32)

  helix = scene.helix
  arrays = {"measurement": measurement, "intensity": maps.intensity, "depth": maps.depth,
            "trajectory": scene.trajectory}
  if spec.store_clean:
    arrays["clean"] = clean
  if albedo is not None:
    arrays["albedo"] = albedo
  attrs = {
      "split": split, "index": int(index), "seed": seed, "efficiency": efficiency,
      "photons": photons, "signal_scale": scale, "ambient": ambient, "dark_counts": dark,
      "jitter": "none" if spec.jitter is None else str(spec.jitter),
      "frame_rate": scene.frame_rate, "helix_center": helix.center, "helix_axis": helix.axis,
      "helix_ref": helix.ref, "helix_radius": helix.radius, "helix_pitch": helix.pitch,
      "helix_phase": helix.phase, "helix_angular_speed": helix.angular_speed,
      "dynamic_index": scene.dynamic_index, "render_depth_range": np.asarray(gated.depth_range),
      "kinds": json.dumps([o.kind for o in scene.objects]),
      "scene": json.dumps(scene.describe()),
  }
  if scene.motion != "helix" or scene.spin_speed:  # options added later: absent by default
    attrs["motion"] = scene.motion
    attrs["spin_speed"] = scene.spin_speed
  if fm is not None:
    attrs["physics"] = fm.describe()
    attrs["family"] = fm.family
  return {"name": sequence_name(split, index), "arrays": arrays, "attrs": attrs}
