"""Realism audit: the real preset's simulated inputs beside the measured scans, as the network sees them.

    python -m experiments.studies.realism [--config real] [--designs base mix] [--data-dir DIR]
        [--sequences 16] [--out experiments/studies/realism/results/realism.md]

Inputs are what the network reads: ``[T, h, w]`` counts of the preset's
bins, under-scanned by its stride. Measured: each scan of ``--data-dir``
(default: ``../shared/data/real``, else the shipped scans) read with the
published preparation (:func:`nlosjax.data.io.load_measurement`) and summed to
the preset's bin width, under-scanned at every one of the ``stride^2``
offsets. Simulated: the middle frames of ``--sequences`` test sequences of
each design's data (``base``: the preset's; ``mix``: the preset with its
forward model drawn from :class:`nlosjax.data.dataset.physics.PhysicsMix`),
written to ``runs/data/<stem>-<design>-audit-<digest>.h5`` if absent.

Per input (:func:`features`): counts per scan point (log10 of the mean, and
their spread), signal-to-background ratio, width of the first return, the
falloff of the return with its distance (slope of log signal on log
distance over scan points), the early-to-late background ratio, the share of
scan points with a return, and the histogram shape around the return (mean
over scan points aligned at their peak). One number for the whole: the
held-out balanced accuracy of a small classifier (:func:`classify`:
logistic regression on the standardised features) telling a measured input
from a simulated one, leave-one-scan-out (each fold holds out one measured
scan and a share of the simulated sequences); 50 % means indistinguishable.
Writes the report and ``<out stem>.png`` (the aligned shapes and two
features by design).
"""

from __future__ import annotations

import json
import pathlib
import sys

import numpy as np

#: This study's results folder: its reports, figures and JSON records.
RESULTS = pathlib.Path(__file__).resolve().parent / "results"

#: Bins before and after the peak of the aligned histogram shape.
SHAPE_BEFORE, SHAPE_AFTER = 3, 12
SCALARS = ("log10_counts", "counts_spread", "log10_sbr", "return_width", "falloff_slope",
           "background_ratio", "signal_share")
FEATURES = SCALARS + tuple(f"shape_{k:+d}" for k in range(-SHAPE_BEFORE, SHAPE_AFTER + 1))
DESIGNS = ("base", "mix")


def features(x: np.ndarray, bin_length: float) -> np.ndarray:
  """Summary features ``[len(FEATURES)]`` of one input ``x [T, h, w]`` of counts (module docstring).

  ``bin_length``: metres of round-trip path per bin (a return at bin ``k`` is
  ``k bin_length / 2`` away).
  """
  x = np.asarray(x, np.float64)
  T = x.shape[0]
  h = x.reshape(T, -1)                                     # [T, P]
  total = h.sum(0)
  bg = np.median(h, axis=0)                                # per point: the flat floor
  excess = np.clip(h - bg, 0, None)
  signal = excess.sum(0)
  noise = np.sqrt(np.maximum(bg, 0.25) * T)
  has = signal > 5 * noise
  smooth = np.apply_along_axis(lambda v: np.convolve(v, np.ones(3) / 3, "same"), 0, excess)
  peak = np.argmax(smooth, axis=0)
  pts = np.flatnonzero(has) if has.any() else np.arange(h.shape[1])
  shape = np.zeros(SHAPE_BEFORE + SHAPE_AFTER + 1)
  for p in pts:
    lo, hi = peak[p] - SHAPE_BEFORE, peak[p] + SHAPE_AFTER + 1
    seg = np.zeros(shape.size)
    src = excess[max(lo, 0):min(hi, T), p]
    seg[max(0, -lo):max(0, -lo) + src.size] = src
    shape += seg / max(seg.max(), 1e-12)
  shape /= max(shape.max(), 1e-12)
  above = shape >= 0.5
  width = float(above.sum())                               # bins at half maximum or more
  dist = (peak + 0.5) * bin_length / 2
  if has.sum() >= 3 and np.ptp(np.log(dist[has])) > 0:
    slope = float(np.polyfit(np.log(dist[has]), np.log(signal[has] + 1e-9), 1)[0])
  else:
    slope = 0.0
  q = max(T // 4, 1)
  early, late = h[:q].mean(), h[-q:].mean()
  sbr = signal[pts].sum() / max(bg[pts].sum() * T, 1e-9)
  scal = [np.log10(max(total.mean(), 1e-9)), float(np.std(np.log10(total + 1)) if total.size else 0.0),
          np.log10(max(sbr, 1e-6)), width, slope, float(np.log10((early + 1e-3) / (late + 1e-3))),
          float(has.mean())]
  return np.asarray(scal + shape.tolist(), np.float64)


def measured_inputs(files, bin_width: float, num_bins: int, stride: int) -> dict:
  """``scene -> [stride^2, T, h, w]`` float64: each scan at the preset's bins, under-scanned at every offset."""
  from nlosjax.data import io
  out = {}
  for path in files:
    x, setup = io.load_measurement(path)
    factor = int(round(bin_width / setup.bin_width))
    T = min(num_bins, x.shape[0] // factor)
    x = x[:T * factor].reshape(T, factor, *x.shape[1:]).sum(1)
    name = pathlib.Path(path).stem.removeprefix("data_")
    out[name] = np.stack([x[:, a::stride, b::stride] for a in range(stride) for b in range(stride)])
  return out


def audit_config(base: dict, design: str, sequences: int) -> dict:
  """The data config of a design's audit file: ``sequences`` test sequences of 4 frames.

  ``base``: the preset's scenes and detector by the transport renderer alone (no physics mix);
  ``mix``: the preset's physics mix (the default :class:`~nlosjax.data.dataset.physics.PhysicsMix`
  with the preset's share of retroreflective objects where it has none). The file is named after a
  digest of its specification, so a changed preset never reads another one's file.
  """
  import copy
  import hashlib

  from nlosjax.data.dataset import DatasetSpec, PhysicsMix
  cfg = copy.deepcopy(base)
  data = cfg["data"]
  physics = data.pop("physics", None)
  retro = (PhysicsMix.from_dict(physics).retroreflective if physics is not None
           else data.get("retroreflective", 0.2))
  if design == "mix":
    data.update(renderer="mix", retroreflective=0.0, physics=physics or {"retroreflective": retro})
  else:
    data.update(renderer="transport", retroreflective=retro)
  data["num_sequences"] = {"train": 0, "test": sequences}
  data["frames"] = 4
  key = json.dumps(DatasetSpec.from_config(data).generation_key(), sort_keys=True, default=str)
  digest = hashlib.sha256(key.encode()).hexdigest()[:6]
  stem = pathlib.PurePosixPath(data["path"]).stem
  data["path"] = str(pathlib.PurePosixPath(data["path"]).with_name(f"{stem}-{design}-audit-{digest}.h5"))
  return cfg


def simulated_inputs(cfg: dict) -> tuple[np.ndarray, np.ndarray]:
  """``(inputs [N, T, h, w], sequence [N])``: frames 1 and 2 of every test sequence, under-scanned."""
  from nlosjax import train as T
  from nlosjax.data.dataset import open_dataset
  path = pathlib.Path(cfg["data"]["path"])
  T.ensure_dataset(T.RunConfig.from_dict(cfg), path)
  data = cfg["data"]
  s, o = int(data["input_stride"]), int(data["input_offset"])
  xs, seq = [], []
  with open_dataset(path) as ds:
    for i, name in enumerate(ds.names("test")):
      m = ds.read(name, "measurement", frames=slice(1, 3), stride=s, offset=o)
      xs.append(np.asarray(m, np.float64))
      seq += [i] * len(m)
  return np.concatenate(xs), np.asarray(seq)


def _fit_logistic(X, y, l2=1.0, iters=50):
  """Logistic regression by Newton's method with an L2 penalty (not on the bias); returns ``(w, b)``."""
  n, d = X.shape
  A = np.concatenate([X, np.ones((n, 1))], 1)
  w = np.zeros(d + 1)
  reg = np.full(d + 1, l2)
  reg[-1] = 0.0
  sw = np.where(y == 1, 0.5 / max(y.sum(), 1), 0.5 / max((1 - y).sum(), 1)) * n   # balanced classes
  for _ in range(iters):
    p = 1 / (1 + np.exp(-np.clip(A @ w, -30, 30)))
    g = A.T @ (sw * (p - y)) + reg * w
    H = (A * (sw * p * (1 - p))[:, None]).T @ A + np.diag(reg) + 1e-9 * np.eye(d + 1)
    step = np.linalg.solve(H, g)
    w -= step
    if np.abs(step).max() < 1e-8:
      break
  return w[:-1], w[-1]


def classify(measured: dict, sim: np.ndarray, sim_seq: np.ndarray, l2: float = 1.0) -> dict:
  """Held-out balanced accuracy, leave-one-scan-out (module docstring).

  Args:
    measured: ``scene -> [n, D]`` features of the measured inputs.
    sim: ``[N, D]`` features of the simulated inputs; ``sim_seq [N]`` their sequences.
  Returns:
    ``{"accuracy": mean balanced accuracy, "folds": [{"scene", "measured_acc", "simulated_acc"}]}``.
  """
  scenes = sorted(measured)
  seqs = np.unique(sim_seq)
  folds = []
  for k, scene in enumerate(scenes):
    test_seq = seqs[k::len(scenes)]
    tr_m = np.concatenate([measured[s] for s in scenes if s != scene])
    tr_s = sim[~np.isin(sim_seq, test_seq)]
    X = np.concatenate([tr_m, tr_s])
    mu, sd = X.mean(0), X.std(0) + 1e-9
    y = np.concatenate([np.ones(len(tr_m)), np.zeros(len(tr_s))])
    w, b = _fit_logistic((X - mu) / sd, y, l2)

    def pred(Z):
      return ((Z - mu) / sd) @ w + b > 0

    te_m, te_s = measured[scene], sim[np.isin(sim_seq, test_seq)]
    folds.append({"scene": scene, "measured_acc": float(pred(te_m).mean()),
                  "simulated_acc": float((~pred(te_s)).mean())})
  acc = float(np.mean([(f["measured_acc"] + f["simulated_acc"]) / 2 for f in folds]))
  return {"accuracy": acc, "folds": folds}


def _stat_cell(v) -> str:
  v = np.asarray(v, np.float64)
  if v.size == 1:
    return f"{v[0]:.3g}"
  return f"{np.median(v):.3g} [{np.percentile(v, 5):.3g}, {np.percentile(v, 95):.3g}]"


def plot(meas: dict, sims: dict, path: pathlib.Path) -> None:
  """Aligned return shapes and two features: measured scans against each design's simulated inputs."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  k = np.arange(-SHAPE_BEFORE, SHAPE_AFTER + 1)
  sh = slice(len(SCALARS), None)
  fig, ax = plt.subplots(1, 2, figsize=(9, 3.4))
  for design, (F, _) in sims.items():
    ax[0].plot(k, np.median(F[:, sh], 0), lw=2, label=f"simulated ({design})")
    ax[1].scatter(F[:, 2], F[:, 0], s=8, alpha=0.5, label=f"simulated ({design})")
  for F in meas.values():
    ax[0].plot(k, F[:, sh].mean(0), "k--", lw=1, alpha=0.7)
    ax[1].scatter(F[:, 2], F[:, 0], s=14, marker="x", color="k")
  ax[0].set_xlabel("bins from the peak")
  ax[0].set_ylabel("aligned return (peak 1)")
  ax[0].set_title("return shape (dashed: measured scans)", fontsize=9)
  ax[1].set_xlabel("log10 signal-to-background")
  ax[1].set_ylabel("log10 counts per scan point")
  ax[1].set_title("x: measured inputs", fontsize=9)
  ax[0].legend(fontsize=7)
  fig.tight_layout()
  fig.savefig(path, dpi=90)
  plt.close(fig)


def main(argv=None) -> int:
  from experiments.cli import config_parser, parse_config
  from experiments.provenance import provenance
  from experiments.studies.real_undersampling import default_files
  from nlosjax.physics.setup import SPEED_OF_LIGHT
  parser = config_parser(__doc__.split("\n\n")[0])
  parser.set_defaults(config="real")
  parser.add_argument("--designs", nargs="+", choices=DESIGNS, default=list(DESIGNS))
  parser.add_argument("--data-dir", default=None, help="folder of measured .mat scans")
  parser.add_argument("--sequences", type=int, default=16, help="simulated test sequences per design")
  parser.add_argument("--out", default=str(RESULTS / "realism.md"))
  argv = sys.argv[1:] if argv is None else list(argv)
  args, base, _ = parse_config(parser, argv)
  data = base["data"]
  stride, bw, T = int(data["input_stride"]), float(data["bin_width"]), int(data["num_bins"])
  bin_length = SPEED_OF_LIGHT * bw
  files = default_files(args.data_dir)
  meas_x = measured_inputs(files, bw, T, stride)
  meas = {s: np.stack([features(v, bin_length) for v in x]) for s, x in meas_x.items()}
  sims, results = {}, {}
  for design in args.designs:
    cfg = audit_config(base, design, args.sequences)
    x, seq = simulated_inputs(cfg)
    F = np.stack([features(v, bin_length) for v in x])
    sims[design] = (F, seq)
    results[design] = classify(meas, F, seq)
    results[design]["data"] = cfg["data"]["path"]
  out = pathlib.Path(args.out)
  figure = out.with_suffix(".png")
  plot(meas, sims, figure)
  cmd = "python -m experiments.studies.realism " + " ".join(argv)
  lines = ["# Realism audit: simulated inputs of the real preset beside the measured scans", ""]
  lines += provenance(cmd.strip()) + [""]
  lines += [f"Preset `{args.config}`: {T} bins of {bw * 1e12:.0f} ps, input every {stride}th scan point "
            f"({data['grid'] // stride} x {data['grid'] // stride}). Measured: {len(files)} scans "
            f"({', '.join(sorted(meas))}), each under-scanned at its {stride * stride} offsets. Simulated: "
            f"frames 1 and 2 of {args.sequences} test sequences per design "
            + ", ".join(f"(`{d}`: `{r['data']}`)" for d, r in results.items()) + f". Figure: `{figure.name}`.", ""]
  lines += ["## The held-out classifier", "",
            "Logistic regression on the standardised features below, leave-one-scan-out (each fold "
            "holds out one measured scan and an equal share of the simulated sequences); balanced "
            "accuracy (mean of the two classes' accuracies), averaged over folds. 50 % = the classifier "
            "cannot tell them apart; goal ≤ 60 %.", "",
            "| design | held-out accuracy | "
            + " | ".join(f"fold {s} (measured / simulated)" for s in sorted(meas)) + " |",
            "|---|---|" + "---|" * len(meas)]
  for d, r in results.items():
    lines.append(f"| {d} | {100 * r['accuracy']:.0f} % | " + " | ".join(
        f"{100 * f['measured_acc']:.0f} / {100 * f['simulated_acc']:.0f} %" for f in r["folds"]) + " |")
  lines += ["", "## What the network sees", "",
            "Measured: one value per scan (median over its offsets). Simulated: median [5 %, 95 %] over "
            "inputs. `log10_counts`: mean counts per scan point; `counts_spread`: std of log10 counts "
            "over scan points; `log10_sbr`: the return's counts over the background's (the median bin "
            "as the floor); `return_width`: bins of the aligned mean return at half maximum or more; "
            "`falloff_slope`: slope of log return counts on log distance over scan points (−2 for "
            "r⁻², −4 for r⁻⁴ at fixed albedo); `background_ratio`: log10 of the first quarter's mean "
            "count over the last quarter's; `signal_share`: share of scan points with a return.", "",
            "| feature | " + " | ".join(sorted(meas)) + " | " + " | ".join(f"simulated ({d})" for d in sims) + " |",
            "|---|" + "---|" * (len(meas) + len(sims))]
  for i, name in enumerate(SCALARS):
    lines.append(f"| {name} | " + " | ".join(f"{np.median(meas[s][:, i]):.3g}" for s in sorted(meas)) + " | "
                 + " | ".join(_stat_cell(F[:, i]) for F, _ in sims.values()) + " |")
  lines += ["", "Aligned return shape (peak 1), bins from the peak:", "",
            "| bin | " + " | ".join(sorted(meas)) + " | " + " | ".join(f"simulated ({d})" for d in sims) + " |",
            "|---|" + "---|" * (len(meas) + len(sims))]
  for j in range(SHAPE_BEFORE + SHAPE_AFTER + 1):
    i = len(SCALARS) + j
    lines.append(f"| {j - SHAPE_BEFORE:+d} | " + " | ".join(f"{np.median(meas[s][:, i]):.2f}" for s in sorted(meas))
                 + " | " + " | ".join(f"{np.median(F[:, i]):.2f}" for F, _ in sims.values()) + " |")
  out.parent.mkdir(parents=True, exist_ok=True)
  out.write_text("\n".join(lines) + "\n")
  out.with_suffix(".json").write_text(json.dumps(
      {"classifier": results, "features": list(FEATURES),
       "measured": {s: F.tolist() for s, F in meas.items()},
       "simulated": {d: {"features": F.tolist(), "sequence": seq.tolist()} for d, (F, seq) in sims.items()}},
      indent=1) + "\n")
  print(out.read_text())
  return 0
