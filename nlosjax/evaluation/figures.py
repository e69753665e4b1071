"""Figures of an evaluation: images side by side, training curves.

Both write a PNG with matplotlib's Agg backend (no display needed).
"""

from __future__ import annotations

import numpy as np

from nlosjax.evaluation.report import TABLE_METHODS, label

__all__ = ["plot_comparison", "plot_training_curves"]


def plot_comparison(images: dict, path, *, frames: int = 3, max_depth: float | None = None) -> None:
  """Intensity (top) and depth (bottom) rows per test frame: ground truth, then each method."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  methods = ["gt"] + [m for m in TABLE_METHODS if m in images]
  n = min(frames, len(images["gt"]["intensity"]))
  idx = np.linspace(0, len(images["gt"]["intensity"]) - 1, n).round().astype(int)
  dmax = max_depth or float(np.max(images["gt"]["depth"])) or 1.0
  fig, axes = plt.subplots(2 * n, len(methods), figsize=(1.6 * len(methods), 3.2 * n), squeeze=False)
  for r, k in enumerate(idx):
    for c, m in enumerate(methods):
      for j, (key, kw) in enumerate((("intensity", dict(cmap="gray", vmin=0, vmax=1)),
                                     ("depth", dict(cmap="viridis", vmin=0, vmax=dmax)))):
        ax = axes[2 * r + j, c]
        ax.imshow(images[m][key][k], **kw)
        ax.set_xticks([])
        ax.set_yticks([])
        if r == 0 and j == 0:
          ax.set_title("GT" if m == "gt" else label(m), fontsize=9)
        if c == 0:
          ax.set_ylabel(f"frame {k}\n{key}", fontsize=8)
  fig.suptitle(f"intensity (gray, [0, 1]) and depth (viridis, 0-{dmax:.2f} m)", fontsize=9)
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)


def plot_training_curves(logs: dict, path) -> None:
  """Total loss and each term against step, one line per variant."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  keys = ["loss", "pf", "t", "int", "dep"]
  fig, axes = plt.subplots(1, len(keys), figsize=(3.2 * len(keys), 2.8))
  for ax, k in zip(axes, keys):
    for variant, rows in logs.items():
      rows = [r for r in rows if k in r]
      if rows:
        ax.plot([r["step"] for r in rows], [r[k] for r in rows], label=label(variant))
    ax.set_title(k)
    ax.set_xlabel("step")
    ax.set_yscale("log")
  axes[0].legend()
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)
