"""The Markdown report (``real.md``): tables, per-reference columns, timing, the networks' data."""

from __future__ import annotations

import json
import pathlib

import numpy as np

from experiments.studies.real_undersampling.ablation import ablation_lines, adaptation_lines, aligned_lines
from experiments.studies.real_undersampling.protocol import (
  CAPTURE_BIN_WIDTH,
  CSA_TAU_REL,
  DEFAULT_PRETRAINED,
  LABELS,
  REFERENCES,
  UNTRAINED,
  over_scenes,
)


def _table(results) -> list[str]:
  strides = results["strides"]
  methods = results["methods"]
  scenes = list(results["scenes"])
  lines = []
  for stride in strides:
    grid = 64 // stride
    rows, by_ref = [], []
    for m in methods:
      cells, ps, ss = [], [], []
      per_ref = {r: [] for r in REFERENCES}
      for sc in scenes:
        s = results["scenes"][sc]["scores"].get((m, stride))
        if s is None:
          cells.append("–")
          continue
        cells.append(f"{s['psnr']:.2f} / {s['ssim']:.3f}")
        ps.append(s["psnr"])
        ss.append(s["ssim"])
        for r, v in s["vs"].items():
          per_ref[r].append(v)
      mean = f"**{np.mean(ps):.2f} / {np.mean(ss):.3f}**" if ps else "–"
      rows.append(f"| {LABELS[m]} | " + " | ".join(cells) + f" | {mean} |")
      ref_cells = [(f"{np.mean([v['psnr'] for v in per_ref[r]]):.2f} / "
                    f"{np.mean([v['ssim'] for v in per_ref[r]]):.3f}") if per_ref[r] else "(own)"
                   for r in REFERENCES]
      by_ref.append(f"| {LABELS[m]} | " + " | ".join(ref_cells) + f" | {mean} |")
    floor = _zero_floor(results, scenes)
    by_ref.append("| *All-zero image (floor)* | " + " | ".join(f"{floor['vs'][r]:.2f} / –" for r in REFERENCES)
                  + f" | {floor['mean']:.2f} / – |")
    rows.append("| *All-zero image (floor)* | " + " | ".join(f"{floor['scenes'][sc]:.2f} / –" for sc in scenes)
                + f" | {floor['mean']:.2f} / – |")
    lines += [f"### Input {grid} × {grid} (stride {stride}): intensity PSNR (dB) / SSIM, mean over scenes, "
              "against each full-scan reconstruction", "",
              "| method | " + " | ".join(f"vs {LABELS[r]} 64 × 64" for r in REFERENCES)
              + " | mean of the columns |",
              "|---|" + "---|" * (len(REFERENCES) + 1), *by_ref, "",
              f"Per scene (input {grid} × {grid}; each cell the mean over the references but the "
              "method's own; the all-zero image's over every reference):", "",
              "| method | " + " | ".join(scenes) + " | mean |",
              "|---|" + "---|" * (len(scenes) + 1), *rows, ""]
  return lines


def _zero_floor(results, scenes) -> dict:
  """The all-zero image's intensity PSNR (dB) against each reference: the score a dark image gets.

  ``{"vs": {reference: mean over scenes}, "scenes": {scene: mean over references}, "mean"}``
  (:func:`nlosjax.metrics.psnr_zero`); a reconstruction near it has drawn little of the scene.
  """
  from nlosjax import metrics
  per = {sc: {r: float(metrics.psnr_zero(np.asarray(results["scenes"][sc]["references"][r], np.float32)))
              for r in REFERENCES} for sc in scenes}
  vs = {r: float(np.mean([per[sc][r] for sc in scenes])) for r in REFERENCES}
  by_scene = {sc: float(np.mean(list(per[sc].values()))) for sc in scenes}
  return {"vs": vs, "scenes": by_scene, "mean": float(np.mean(list(by_scene.values())))}


def _time_lines(results) -> list[str]:
  """Seconds per scan of each method and input, as :func:`run` measured them (one frame each).

  *first*: the first scene's first call, which pays tracing and XLA
  compilation where nothing compiled it before (the classic methods' full-scan
  references have the same shape and compiled it already); *per frame*: the
  median over scenes of a second call on the same scan, compiled.
  """
  scenes = list(results["scenes"])
  if not scenes:
    return []
  lines = ["Seconds per scan in this process, on the machine above (*first*: the first call on"
           f" {scenes[0]}, tracing and compilation included; *per frame*: the median over the scenes of"
           " a second call on the same scan, compiled (CSA: on the first scan only); the networks' times"
           " include moving the physics layer to the scan's setup and the time binning):", "",
           "| method | " + " | ".join(f"{64 // s} × {64 // s} first | {64 // s} × {64 // s} per frame"
                                      for s in results["strides"]) + " |",
           "|---|" + "---|---|" * len(results["strides"])]
  for m in results["methods"]:
    cells = []
    for stride in results["strides"]:
      rows = over_scenes(results, m, stride)
      again = [r["again_s"] for r in rows if "again_s" in r]
      cells += [f"{rows[0]['time_s']:.2f}" if rows else "–",
                f"{np.median(again):.2f}" if again else "–"]
    lines.append(f"| {LABELS[m]} | " + " | ".join(cells) + " |")
  return lines + [""]


def _winner_lines(results) -> list[str]:
  lines = []
  classic = [m for m in results["methods"] if m in UNTRAINED]
  models = [m for m in results["methods"] if m not in UNTRAINED]
  for stride in results["strides"]:
    means = {}
    for m in results["methods"]:
      vals = over_scenes(results, m, stride)
      if vals:
        means[m] = (np.mean([v["psnr"] for v in vals]), np.mean([v["ssim"] for v in vals]))
    if not classic or not means:
      continue
    best_c = max(classic, key=lambda m: means[m][0])
    best_cs = max(classic, key=lambda m: means[m][1])
    for v in models:
      if v not in means:
        continue
      beats_p = means[v][0] > means[best_c][0]
      beats_s = means[v][1] > means[best_cs][1]
      lines.append(
          f"- stride {stride}: {LABELS[v]} mean PSNR {means[v][0]:.2f} dB vs the best without training"
          f" ({LABELS[best_c]}) {means[best_c][0]:.2f} dB -> {'beats' if beats_p else 'does not beat'}"
          f" every method without training; mean SSIM {means[v][1]:.3f} vs best ({LABELS[best_cs]})"
          f" {means[best_cs][1]:.3f} -> {'beats' if beats_s else 'does not beat'}.")
  return lines



def _network_text(results) -> str:
  """How the networks read the scans: trained geometry and the time binning."""
  trained = results.get("trained") or {}
  if not trained:
    return "no trained network."
  from nlosjax.inference import default_bin_factor
  mcfg = next(iter(trained.values()))[0]
  s = mcfg.setup
  factor = default_bin_factor(s.bin_width, CAPTURE_BIN_WIDTH)   # what for_capture sums
  return (f"the networks on the sparse scan with time summed {factor} × 16 ps ="
          f" {factor * 16} ps (trained on {s.bin_width * 1e12:.0f} ps bins, {s.grid[0]} × {s.grid[1]}"
          f" scans of a {s.wall_size:g} m wall at stride {mcfg.stride}).")


def _layer_variants(results) -> str:
  """Which operators each network's physics layer uses (``physics_variant``; USM: refined LCT)."""
  parts = []
  for v, (mcfg, _) in (results.get("trained") or {}).items():
    variant = getattr(mcfg, "physics_variant", "refined")
    method = getattr(mcfg, "physics", "lct")
    parts.append(f"{LABELS[v]} {variant} {'phasor' if method == 'phasor' else 'LCT'}")
  return ", ".join(parts) or "none"


def _binned_lines(results, binned) -> list[str]:
  """The table of :func:`binned_classic`: classic scores at 16 ps beside those at the networks' bins."""
  if not binned:
    return []
  width = f"{binned['bin_width'] * 1e12:.0f} ps"
  lines = [
      f"What the networks' time bins cost: phasor and RSD on the same sparse scans summed to"
      f" {binned['bin_factor']} × 16 ps = {width}, the networks' input (`binned_classic`;"
      + "".join(f" {LABELS[m]} sampling_coeff per scene "
                + " / ".join(f"{o.get('sampling_coeff', 2.0):.3g}" for o in opts) + ";"
                for m, opts in binned["options"].items())
      + " means over scenes, PSNR (dB) / SSIM: mean over the same references). A *refined operators*"
      " row is that method with the refined operators (`variant=\"refined\"`: centred wavelet, plain"
      " bin averaging from t to v) in place of the public ones: on the same input, what a physics"
      " layer's operators cost or gain before anything learned acts. The networks' physics layers: "
      + _layer_variants(results) + ":", "",
      f"| method | input | at 16 ps | at {width} |", "|---|---|---|---|"]
  for (m, stride), r in binned["scores"].items():
    base, _, variant = m.partition("/")
    if variant:     # its own scores at 16 ps
      p16, s16 = r["psnr_16"], r["ssim_16"]
      label = f"{LABELS[base]}, {variant} operators"
    else:
      vals = over_scenes(results, m, stride)
      p16, s16, label = np.mean([v["psnr"] for v in vals]), np.mean([v["ssim"] for v in vals]), LABELS[m]
    g = 64 // stride
    lines.append(f"| {label} | {g} × {g} | {p16:.2f} / {s16:.3f} | {r['psnr']:.2f} / {r['ssim']:.3f} |")
  return lines + [""]


def write_report(results, out: pathlib.Path, *, timing=None, warm=None, synthetic=None,
                 binned=None, ablation=None, adaptation=None, aligned=(), facts: list[str],
                 elapsed: float, figures: list[str], notes: str = "") -> None:
  lines = ["# Under-scanning on measured scans", ""] + facts + [
      f"- Wall time: {elapsed / 60:.1f} min; numpy {np.__version__}",
      "- Scans: " + ", ".join(f"`{pathlib.Path(e['file']).name}`" for e in results["scenes"].values()) +
      " (O'Toole et al. 2018, 64 × 64 × 512 after the published preparation, 16 ps bins)",
      "- Protocol: see the docstring of `experiments/studies/real_undersampling/__init__.py`: references = each"
      " classic method on the full 64 × 64 scan, a method scored against every reference but its"
      " own; sparse scans = scan points `stride // 2 + stride i`;"
      " classic methods on the sparse scan interpolated to 64 × 64 (LCT snr 0.8 and FBP with"
      " the retroreflective t² falloff, f-k / phasor / RSD defaults); CSA on the sparse scan itself,"
      " a masked 64 × 64 grid (t² falloff, 200 FISTA iterations, tau_rel "
      + ", ".join(f"{v:g} at stride {k}" for k, v in sorted(CSA_TAU_REL.items()))
      + ", chosen on the `real` preset's simulated validation split: `experiments/studies/csa/results/csa_choice.md`); "
      + _network_text(results),
      "",
  ]
  lines += _table(results)
  lines += _time_lines(results)
  if notes:
    lines += [notes, ""]
  wl = _winner_lines(results)
  if wl:
    lines += ["Does the trained network beat every method without training, the classic ones and CSA"
              " (means over scenes)?", "", *wl, ""]
  lines += _binned_lines(results, binned)
  lines += ablation_lines(results, ablation)
  lines += adaptation_lines(results, adaptation)
  for a in aligned or ():
    lines += aligned_lines(results, a)
  if synthetic:
    lines += [
        f"In-domain check (same code, the networks' own data): {synthetic['frames']} frames of"
        f" the synthetic test split of `{synthetic['file']}` at stride {synthetic['stride']},"
        " scored against the ground-truth intensity (CSA with the options above; classic methods with default options"
        + "".join(f", {LABELS[m]} " + ", ".join(f"{k} {v:.3g}" for k, v in o.items())
                  for m, o in synthetic.get("options", {}).items() if o)
        + "; the adaptation is the identity there: bin factor 1, the trained wavelet):", "",
        "| method | PSNR (dB) | SSIM |", "|---|---|---|"]
    for m, r in synthetic["scores"].items():
      lines.append(f"| {LABELS[m]} | {r['psnr']:.2f} | {r['ssim']:.3f} |")
    lines.append("")
  lines += ["Figures: " + ", ".join(f"[{f}]({f})" for f in figures), ""]
  for f in figures:
    lines += [f"![{f}]({f})", ""]
  if timing:
    lines += [
        "## `experiments.reconstruct` vs the NumPy/SciPy twins (64 × 64 × 512)",
        "",
        f"Scan `{timing['file']}`; median of {timing['repeats']} fresh processes each. CLI columns"
        " are what `python -m experiments.reconstruct FILE --method M --out DIR` reports: *load*"
        " (read + prepare the .mat) and *reconstruct* (operators, tracing, XLA compilation and"
        " the run), without the Python/JAX import and the PNG writing; *cold* = no compilation"
        " cache (`--no-cache`), *cached* = the persistent XLA cache filled by an earlier run."
        " Twin = `experiments/numpy_twins.py` (NumPy/SciPy ports of the public code, `scipy.fft`"
        " on all cores, complex64): load (`scipy.io.loadmat` + the same preparation) + operator"
        " build + one run. *Process* columns are whole `python` processes (imports, writing"
        " PNGs included; the twin's process also imports JAX through `nlosjax.physics.setup`).",
        "",
        "| method | CLI cold load + reconstruct s | CLI cached load + reconstruct s | twin load + build + run s"
        " | CLI cold process s | CLI cached process s | twin process s |",
        "|---|---|---|---|---|---|---|"]
    for m, r in timing["methods"].items():
      c, k, t = r["cli_cold"], r["cli_cached"], r["twin"]
      lines.append(f"| {m} | {c['load_s'] + c['reconstruct_s']:.2f} | {k['load_s'] + k['reconstruct_s']:.2f} |"
                   f" {t['load_s'] + t['build_s'] + t['run_s']:.2f} | {c['process_s']:.2f} |"
                   f" {k['process_s']:.2f} | {t['process_s']:.2f} |")
    lines.append("")
  if warm:
    lines += ["Warm runs in one process (operators built, compiled; median of 5):", "",
              "| method | JAX `reconstruct` s | twin run s |", "|---|---|---|"]
    for m, r in warm.items():
      lines.append(f"| {m} | {r['jax_run_s']:.3f} | {r['twin_run_s']:.3f} |")
    lines.append("")
  out.write_text("\n".join(lines))


def training_data(checkpoint) -> str:
  """The dataset a trained run read (``data.path`` of its ``config.json``), else the cpu preset's.

  ``checkpoint`` is a workdir, a variant's folder or its ``checkpoints``
  folder; the run's ``config.json`` is in the workdir.
  """
  from experiments.configs import get_config
  default = get_config("cpu")["data"]["path"]
  if not checkpoint:
    return default
  here = pathlib.Path(checkpoint).absolute()
  config = next((d / "config.json" for d in (here, *list(here.parents)[:2])
                 if (d / "config.json").is_file()), None)
  if config is None:
    return default
  return str(json.loads(config.read_text()).get("data", {}).get("path", default))


def pretrained_data(name=None) -> str:
  """The dataset the shipped weights ``name`` were validated on (their provenance's ``data.path``)."""
  from nlosjax import pretrained
  name = name or DEFAULT_PRETRAINED
  variant = next(v for n, v in pretrained.shipped() if n == name)
  prov = pretrained.read_provenance(pretrained.weights_folder(name, variant))
  return str(prov["config"]["data"]["path"])
