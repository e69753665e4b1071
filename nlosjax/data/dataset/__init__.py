"""Dynamic NLOS datasets: simulate sequences, store them in HDF5, load frame triplets.

Each sequence is drawn from its own seed (``sequence_seed(base_seed, split,
index)``): a scene of :mod:`nlosjax.data.scenes`, its noise-free transient
``clean [F, T, H, W]`` (expected incident signal photons per bin; the LCT
operator, the transport renderer or, with ``renderer="mix"``, a forward model
drawn per sequence) and SPAD counts ``measurement [F, T, H, W]``, with
``intensity``/``depth [F, H, W]`` and the dynamic object's ``trajectory [F, 3]``
(metres). Under-scanning happens at load time; :class:`TripletLoader` yields
batches ``{"measurement": [B, 3, T, h, w], "transient": [B, T, H, W], ...}``.
The units, the noise model, the HDF5 layout (:data:`FORMAT_NAME`, version
:data:`FORMAT_VERSION`) and the loader's rules are in ``docs/dataset.md``.

The code, one concern per module; every name is importable from
``nlosjax.data.dataset``:

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
* :mod:`~nlosjax.data.dataset.loader` -- :class:`TripletLoader`, :class:`LoaderOptions` and :func:`prefetch`.
"""

from nlosjax.data.dataset.file import (
  DATASETS,
  FINGERPRINT_RTOL,
  FORMAT_NAME,
  FORMAT_VERSION,
  DynamicDataset,
  WriteResult,
  dataset_digest,
  dataset_fingerprint,
  dataset_identity,
  extend_dataset,
  fingerprint_differences,
  fingerprint_distance,
  open_dataset,
  write_dataset,
)
from nlosjax.data.dataset.file import _partial_path as _partial_path  # private; the tests use it
from nlosjax.data.dataset.loader import LoaderOptions, TripletLoader, prefetch
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
    "LoaderOptions",
    "ForwardModel",
    "PhysicsMix",
    "dataset_digest",
    "dataset_fingerprint",
    "dataset_identity",
    "fingerprint_differences",
    "fingerprint_distance",
    "FINGERPRINT_RTOL",
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
