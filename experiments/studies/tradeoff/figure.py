"""The plot ``tradeoff.png``: time per frame against intensity PSNR, the Pareto front drawn."""

from __future__ import annotations

import numpy as np

from experiments.studies.tradeoff.pareto import pareto_front, pareto_points


def plot(res: dict, path) -> None:
  """Time per frame (log) against intensity PSNR; front of the default-capture points drawn."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  pts = pareto_points(res)
  default = [p for p in pts if p["capture"] == "default"]
  front = pareto_front([p["time"] for p in default], [p["psnr"] for p in default])
  fig, ax = plt.subplots(figsize=(8.5, 5.5))
  colours = {"classic": "tab:blue", "learned": "tab:red"}
  for kind, marker in (("classic", "o"), ("learned", "*")):
    d = [p for p in default if p["kind"] == kind]
    ax.scatter([1e3 * p["time"] for p in d], [p["psnr"] for p in d], marker=marker,
               s=90 if kind == "learned" else 40, c=colours[kind], label=f"{kind} (default capture)",
               zorder=3)
    c = [p for p in pts if p["kind"] == kind and p["capture"] != "default"]
    ax.scatter([1e3 * p["time"] for p in c], [p["psnr"] for p in c], marker=marker,
               s=70 if kind == "learned" else 30, facecolors="none", edgecolors=colours[kind],
               alpha=0.6, label=f"{kind}, other capture (density, exposure)", zorder=2)
  fp = sorted([p for p, f in zip(default, front) if f], key=lambda p: p["time"])
  xs, ys = [], []
  for p in fp:
    if xs:
      xs.append(1e3 * p["time"])
      ys.append(ys[-1])
    xs.append(1e3 * p["time"])
    ys.append(p["psnr"])
  ax.plot(xs, ys, "k--", lw=1, label="Pareto front (default capture)", zorder=1)
  for p in fp:
    ax.annotate(p["label"], (1e3 * p["time"], p["psnr"]), textcoords="offset points",
                xytext=(4, 4), fontsize=7)
  others = [p for p in default if p not in fp and p["knob"] == "method"]
  for p in others:
    ax.annotate(p["label"], (1e3 * p["time"], p["psnr"]), textcoords="offset points",
                xytext=(4, -9), fontsize=7, color="gray")
  top = max((p["psnr"] for p in default if p["kind"] == "learned"), default=np.inf)
  for p in pts:
    if p["capture"] != "default" and p["kind"] == "classic" and p["psnr"] >= top:
      ax.annotate(p["label"], (1e3 * p["time"], p["psnr"]), textcoords="offset points",
                  xytext=(4, -3), fontsize=6, color="gray")
  ax.set_xscale("log")
  from matplotlib.ticker import FormatStrFormatter
  ax.xaxis.set_major_formatter(FormatStrFormatter("%g"))
  ax.xaxis.set_minor_formatter(FormatStrFormatter("%g"))
  ax.tick_params(axis="x", which="minor", labelsize=7)
  ax.set_xlabel("time per reconstructed frame (ms, jitted, warm; log scale)")
  ax.set_ylabel("intensity PSNR (dB)")
  ax.set_title(f"Speed vs accuracy, test split ({res['frames']} frames), 2 shared CPU cores",
               fontsize=10)
  ax.grid(True, which="both", alpha=0.3)
  ax.legend(fontsize=7, loc="lower right")
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)
