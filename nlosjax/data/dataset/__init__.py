"""Dynamic NLOS datasets: simulate sequences, store them in HDF5, load frame triplets.

Generation (:func:`simulate_sequence`, :func:`write_dataset`): each sequence
is drawn from its own seed, ``sequence_seed(base_seed, split, index)``; its
scene (:mod:`nlosjax.data.scenes`) is rasterised per frame into an albedo
volume, intensity and depth maps; :func:`nlosjax.physics.render` gives the
noise-free transient (gated to the scene's depth range, :func:`render_setup`),
or, with ``renderer="transport"``, :func:`nlosjax.data.surfaces.render_scene`
renders the objects' whole surfaces by light transport;
the SPAD counts follow :func:`nlosjax.physics.expected_counts` with
per-sequence efficiency ``eta ~ U(efficiency)``, photon budget ``S`` and
ambient light log-uniform in their ranges, dark counts and timing jitter,
drawn by NumPy's Poisson sampler (or :func:`nlosjax.physics.add_spad_noise`
with ``noise_sampler="jax"``). With ``renderer="mix"`` the forward model itself
is drawn per sequence from ``physics`` (:class:`PhysicsMix`: renderer family,
falloffs, cosines, impulse response, background shape, gain, time-zero
offset, early gate; :mod:`~nlosjax.data.dataset.physics`).

Units. ``clean`` is the expected number of *incident* signal photons per time
bin: ``signal_scale * render(albedo)``, with ``signal_scale`` chosen so that
the mean over frames and scan points of ``sum_t clean`` is ``S`` (the budget
is per sequence, so a frame where the object comes closer is brighter). It is
stored with 12 mantissa bits (relative rounding <= 1.2e-4) and values below
1e-6 of its peak set to 0, which makes files 3x smaller; the measurement is
drawn from the stored values. The measurement is ``Poisson(eta * (clean (*)
g + ambient) + dark_counts)`` per bin (``g`` the jitter kernel; ``ambient``
and ``dark_counts`` per bin), i.e. :func:`measurement_rate`.

HDF5 layout (:data:`FORMAT_NAME`, version :data:`FORMAT_VERSION`)::

  /                                  attrs: format, format_version, generator_version,
                                     nlosjax_version, wall_size (m), grid [H, W],
                                     bin_width (s), num_bins, spec (JSON of the DatasetSpec),
                                     seed, num_train, num_test, num_val, background_depth (m),
                                     complete, created
  /sequences/<split>-<index:05d>/    attrs: split ("train" | "test" | "val"), index, seed, efficiency,
                                     photons, signal_scale, ambient (per bin), dark_counts
                                     (per bin), jitter, frame_rate (Hz), helix_center [3],
                                     helix_axis [3], helix_ref [3], helix_radius, helix_pitch,
                                     helix_phase, helix_angular_speed (rad/s), dynamic_index,
                                     render_depth_range [2], kinds (JSON list), scene (JSON),
                                     complete; with a non-default motion also motion
                                     ("helix" | "line"; helix_* then describe the unused
                                     helix, the path is in scene) and spin_speed (rad/s);
                                     with renderer "mix" also family and physics (JSON of
                                     the drawn ForwardModel)
      measurement  [F, T, H, W] uint16 (uint32 when a count exceeds 65535) SPAD counts
      clean        [F, T, H, W] float32 expected incident signal photons (optional)
      albedo       [F, T, H, W] float32 shaded albedo volume (optional)
      intensity    [F, H, W]    float32 in [0, 1]
      depth        [F, H, W]    float32 metres; background_depth (0) where empty
      trajectory   [F, 3]       float64 dynamic object's anchor per frame, metres

Transient-shaped datasets are chunked one frame and one scan row at a time
(``[1, T, 1, W]``) and compressed (gzip + shuffle by default): reading a frame
touches its ``H`` chunks only, an under-scanned read (every ``stride``-th row)
only ``H / stride`` of them. Maps are chunked per frame.

Under-scanning (paper: every 8th scan point, 128 -> 16) happens at load time
(:func:`undersample`: ``x[..., offset::stride, offset::stride]``), so one file
serves several input densities. The under-scanned points are the full grid's
points ``offset, offset + stride, ...``; see :func:`undersampled_positions`.

Triplets (:class:`TripletLoader`): an example is a middle frame ``m`` of a
sequence with input frames ``(m - 1, m, m + 1)``. At sequence ends, ``ends =
"valid"`` (default) uses only ``1 <= m <= F - 2``; ``"replicate"`` uses every
``m`` and repeats the end frame (``(0, 0, 1)`` and ``(F - 2, F - 1, F -
1)``). Batches are ``{"measurement": [B, 3, T, h, w], "transient": [B, T, H,
W], "intensity": [B, H, W], "depth": [B, H, W], "sequence": [B], "frame":
[B], "efficiency": [B]}``; the loader's position is one integer, the global
step (epoch = step // steps_per_epoch; the order within an epoch is a
permutation drawn from ``(seed, epoch)``), so resuming is ``iterate(step)``.

The code, one concern per module; every name is importable from
``nlosjax.data.dataset`` as before the split:

* :mod:`~nlosjax.data.dataset.spec` -- :class:`DatasetSpec` (what determines a
  dataset, from a config's ``data`` section), :data:`SPLITS`,
  :func:`sequence_seed` and :func:`sequence_name`.
* :mod:`~nlosjax.data.dataset.simulate` -- :func:`simulate_sequence` (scene,
  rendering, SPAD counts), :func:`render_setup`, :func:`measurement_rate`.
* :mod:`~nlosjax.data.dataset.physics` -- :class:`PhysicsMix` (the forward
  model as a random variable) and its draws, :class:`ForwardModel`.
* :mod:`~nlosjax.data.dataset.file` -- the HDF5 file format: the writer
  (:func:`write_dataset` with its ``.partial`` resume and worker processes,
  :func:`extend_dataset`) and the reader (:class:`DynamicDataset`,
  :func:`open_dataset`).
* :mod:`~nlosjax.data.dataset.undersampling` -- :func:`undersample`,
  :func:`undersampled_positions`, :func:`undersampled_setup`.
* :mod:`~nlosjax.data.dataset.loader` -- :class:`TripletLoader` and :func:`prefetch`.
"""

from nlosjax.data.dataset.file import (
  DATASETS,
  FORMAT_NAME,
  FORMAT_VERSION,
  DynamicDataset,
  WriteResult,
  extend_dataset,
  open_dataset,
  write_dataset,
)
from nlosjax.data.dataset.file import _partial_path as _partial_path  # private; the tests use it
from nlosjax.data.dataset.loader import TripletLoader, prefetch
from nlosjax.data.dataset.physics import FAMILIES, ForwardModel, PhysicsMix
from nlosjax.data.dataset.simulate import measurement_rate, render_setup, simulate_sequence
from nlosjax.data.dataset.spec import RENDERERS, SPLITS, DatasetSpec, sequence_name, sequence_seed
from nlosjax.data.dataset.undersampling import undersample, undersampled_positions, undersampled_setup

__all__ = [
    "DATASETS",
    "FAMILIES",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "RENDERERS",
    "SPLITS",
    "DatasetSpec",
    "DynamicDataset",
    "ForwardModel",
    "PhysicsMix",
    "TripletLoader",
    "WriteResult",
    "open_dataset",
    "prefetch",
    "measurement_rate",
    "render_setup",
    "sequence_name",
    "sequence_seed",
    "simulate_sequence",
    "undersample",
    "undersampled_positions",
    "undersampled_setup",
    "write_dataset",
    "extend_dataset",
]
