"""The test split of the CPU preset's dataset in memory (:class:`TestSplit`): under-scanned
input windows, the ground truth of the middle frames, re-noising at another exposure.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np


@dataclasses.dataclass
class TestSplit:
  """The test split in memory, full scan grid.

  Attributes:
    setup: the file's Setup (no depth range).
    measurement: per sequence ``[F, T, H, W]`` float32 SPAD counts.
    clean: per sequence ``[F, T, H, W]`` float32 noise-free photons per bin (or None).
    intensity, depth: per sequence ``[F, H, W]``.
    attrs: per sequence ``efficiency``, ``ambient``, ``dark_counts`` (per bin).
    examples: ``[N, 2]`` (sequence, middle frame), middles ``1 .. F - 2``.
  """

  setup: Any
  measurement: list
  clean: list | None
  intensity: list
  depth: list
  attrs: list
  examples: np.ndarray

  @classmethod
  def load(cls, path, split: str = "test") -> "TestSplit":
    from nlosjax.data.dataset import open_dataset
    with open_dataset(path) as ds:
      names = ds.names(split)
      if not names:
        raise ValueError(f"{path}: no {split!r} sequences")
      has_clean = all(ds.has(n, "clean") for n in names)
      meas, clean, inten, depth, attrs, examples = [], [] if has_clean else None, [], [], [], []
      for s, name in enumerate(names):
        meas.append(ds.read(name, "measurement", dtype=np.float32))
        if has_clean:
          clean.append(ds.read(name, "clean", dtype=np.float32))
        inten.append(ds.read(name, "intensity", dtype=np.float32))
        depth.append(ds.read(name, "depth", dtype=np.float32))
        a = ds.sequence_attrs(name)
        attrs.append({k: float(a[k]) for k in ("efficiency", "ambient", "dark_counts")})
        F = meas[-1].shape[0]
        if F < 3:
          raise ValueError(f"{path}: sequence {name} has {F} frames; need >= 3")
        examples += [(s, m) for m in range(1, F - 1)]
      setup = ds.setup
    return cls(setup, meas, clean, inten, depth, attrs, np.asarray(examples, np.int64))

  def __len__(self):
    return len(self.examples)

  def gt(self) -> tuple[np.ndarray, np.ndarray]:
    """``(intensity [N, H, W], depth [N, H, W])`` of the middle frames."""
    return (np.stack([self.intensity[s][m] for s, m in self.examples]),
            np.stack([self.depth[s][m] for s, m in self.examples]))

  def windows(self, stride: int, frames: int, measurement: list | None = None) -> np.ndarray:
    """``[N, frames, T, h, w]`` under-scanned inputs (frame indices clipped at sequence ends).

    Scan points ``stride // 2 + stride * i`` (the model's convention).
    """
    meas = self.measurement if measurement is None else measurement
    half = frames // 2
    out = []
    for s, m in self.examples:
      idx = np.clip(np.arange(m - half, m + half + 1), 0, meas[s].shape[0] - 1)
      out.append(meas[s][idx][..., stride // 2::stride, stride // 2::stride])
    return np.stack(out).astype(np.float32)

  def renoised(self, exposure: float, seed: int = 0) -> list:
    """Per sequence ``[F, T, H, W]`` counts at ``exposure`` times the stored exposure.

    ``add_spad_noise`` of the stored noise-free transient with ``pulses =
    exposure`` (signal), ambient and dark counts times ``exposure``, the
    sequence's efficiency and the measured jitter; seeded by ``(seed, sequence)``.
    """
    import jax

    from nlosjax.physics import add_spad_noise
    if self.clean is None:
      raise ValueError("the dataset stores no clean transients; cannot vary the exposure")
    if not exposure > 0:
      raise ValueError(f"exposure must be > 0, got {exposure!r}")
    key = jax.random.key(seed)
    out = []
    for s, (clean, a) in enumerate(zip(self.clean, self.attrs)):
      out.append(np.asarray(add_spad_noise(
          jax.random.fold_in(key, s), clean, self.setup, pulses=float(exposure),
          efficiency=a["efficiency"], ambient=a["ambient"] * exposure,
          dark_counts=a["dark_counts"] * exposure, jitter="measured"), np.float32))
    return out
