"""Figures beside the report: one image row per method per scene, and the summary."""

from __future__ import annotations

import pathlib

import numpy as np

from experiments.studies.real_undersampling.protocol import ITERATIVE, LABELS, REFERENCES, over_scenes


def write_figures(results, out_dir: pathlib.Path, prefix: str = "real") -> list[str]:
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  names = []
  strides = results["strides"]
  methods = results["methods"]
  cols = [1] + list(strides)
  for scene, entry in results["scenes"].items():
    fig, axes = plt.subplots(len(methods), len(cols), figsize=(2.1 * len(cols), 2.1 * len(methods)),
                             squeeze=False)
    for r, m in enumerate(methods):
      for c, s in enumerate(cols):
        ax = axes[r, c]
        ax.set_xticks([])
        ax.set_yticks([])
        img = entry["images"].get((m, s))
        if img is None:
          ax.set_facecolor("0.85")
          why = "not a\nreference" if m in ITERATIVE else "needs a\nsparse scan"
          ax.text(0.5, 0.5, why, ha="center", va="center", fontsize=7, transform=ax.transAxes)
        else:
          ax.imshow(img, cmap="gray", vmin=0, vmax=1)
          sc = entry["scores"].get((m, s))
          tag = "full-scan reference" if (s == 1 and m in REFERENCES) else (
              f"{sc['psnr']:.1f} dB / {sc['ssim']:.2f}" if sc else "")
          ax.set_title(tag, fontsize=7)
        if c == 0:
          ax.set_ylabel(LABELS[m], fontsize=9)
        if r == 0:
          g = 64 // s
          ax.set_xlabel(f"{g} × {g}" + (" (full)" if s == 1 else f" (stride {s})"), fontsize=8)
          ax.xaxis.set_label_position("top")
    fig.suptitle(f"{scene}: intensity per method (PSNR / SSIM: mean vs the other methods' full-scan images)",
                 fontsize=8)
    fig.tight_layout()
    name = f"{prefix}_{scene}.png"
    fig.savefig(out_dir / name, dpi=100)
    plt.close(fig)
    names.append(name)
  # summary bars
  fig, axes = plt.subplots(1, 2, figsize=(9, 3.2))
  width = 0.8 / max(1, len(strides))
  for k, s in enumerate(strides):
    ps, ss = [], []
    for m in methods:
      vals = over_scenes(results, m, s)
      ps.append(np.mean([v["psnr"] for v in vals]) if vals else np.nan)
      ss.append(np.mean([v["ssim"] for v in vals]) if vals else np.nan)
    x = np.arange(len(methods)) + (k - (len(strides) - 1) / 2) * width
    axes[0].bar(x, ps, width, label=f"{64 // s} × {64 // s}")
    axes[1].bar(x, ss, width, label=f"{64 // s} × {64 // s}")
  for ax, t in zip(axes, ("mean intensity PSNR (dB)", "mean intensity SSIM")):
    ax.set_xticks(np.arange(len(methods)))
    ax.set_xticklabels([LABELS[m] for m in methods], fontsize=8)
    ax.set_title(t, fontsize=9)
  axes[0].legend(fontsize=8)
  fig.tight_layout()
  fig.savefig(out_dir / f"{prefix}_summary.png", dpi=100)
  plt.close(fig)
  return names + [f"{prefix}_summary.png"]
