"""Networks with learned parts zeroed, fitted to each scan (adaptation) or aligned: runs and report lines."""

from __future__ import annotations

import numpy as np

from experiments.studies.real_undersampling.protocol import (
  LABELS,
  REFERENCES,
  UNTRAINED,
  fold_files,
  fold_folder,
  over_scenes,
  run,
  scene_name,
)
from nlosjax.variants import USM

#: What each ablation zeroes in an ST-Mamba network (parameter path prefixes). With
#: ``spread/to_transient`` zero the recovered transient is the skip alone: the sparse
#: scan bilinearly interpolated (times ``skip_gain``); with ``volume/refine/to_volume``
#: zero the volume is the physics layer's normalised reconstruction of that transient.
ABLATIONS = {"no_refinement": ("volume/refine/to_volume",),
             "physics_only": ("spread/to_transient", "volume/refine/to_volume")}
ABLATION_TEXT = {"no_refinement": "refinement zeroed",
                 "physics_only": "spreading residual and refinement zeroed (interpolated scan, physics layer)"}


def _zeroed(params, prefixes):
  """``params`` with every leaf under one of ``prefixes`` (``/``-joined paths) set to 0.

  None unless every prefix names at least one leaf (a network without those parts).
  """
  import jax
  hit = []

  def leaf(path, v):
    name = "/".join(str(getattr(k, "key", k)) for k in path)
    if name.startswith(prefixes):
      hit.append(name)
      return np.zeros_like(v)
    return v
  out = jax.tree_util.tree_map_with_path(leaf, params)
  return out if {p for p in prefixes if any(h.startswith(p) for h in hit)} == set(prefixes) else None


def ablated_models(trained: dict) -> dict:
  """``"<variant>|<ablation>" -> (model_config, params)`` for each network that has the ablated parts.

  USM has no such parts and is skipped. The ablations (:data:`ABLATIONS`) ask how
  much of a network's score on measured scans its learned residuals give or take.
  """
  out = {}
  for v, (mcfg, params) in trained.items():
    for name, prefixes in ABLATIONS.items():
      zeroed = _zeroed(params, prefixes)
      if zeroed is not None:
        out[f"{v}|{name}"] = (mcfg, zeroed)
  return out


def aligned_run(files, strides, results, workdir) -> dict:
  """Each scan scored by the networks of ``python -m experiments.studies.align --workdir WORKDIR`` that left it out.

  Returns the :func:`run` results of ``"<variant>|aligned"`` (scenes without such a network are
  absent), with ``"workdir"`` (its folder's name) and ``"lam"`` (the sorted distinct ``lam`` of
  the folds' ``align.json``, with ``"lam_rule"`` names where a rule set it and the layer aligned).
  """
  import json
  import pathlib

  from nlosjax.pretrained import unflatten_params
  merged = {"strides": list(strides), "methods": [], "scenes": {}, "trained": {},
            "workdir": pathlib.Path(workdir).name, "lam": []}
  lams = set()
  for path in files:
    scene = scene_name(path)
    models = {}
    for v, (mcfg, _) in results["trained"].items():
      finished = fold_files(fold_folder(workdir, v, scene))        # params.npz, align.json
      if finished:
        with np.load(finished[0]) as z:
          models[f"{v}|aligned"] = (mcfg, unflatten_params({k: z[k] for k in z.files}))
        record = json.loads(finished[1].read_text())
        rule = record.get("lam_rule", {}).get("rule")
        layer = record.get("layer", "st_mamba0")      # records before the layer choice: the first block
        lams.add(f"{LABELS[v]} {record['lam']:.4g}" + (f" ({rule})" if rule else "") + f" at {layer}")
    if not models:
      continue
    part = run([path], strides, None, trained=models, classic=False,
               references={scene: results["scenes"][scene]["references"]})
    merged["scenes"][scene] = part["scenes"][scene]
    merged["methods"] = sorted(set(merged["methods"]) | set(models))
  merged["lam"] = sorted(lams)
  return merged


def adapted_models(trained: dict) -> dict:
  """``"<variant>|adapted" -> (model_config, params, True)`` for each ST-Mamba network (not USM)."""
  return {f"{v}|adapted": (mcfg, params, True) for v, (mcfg, params) in trained.items() if v != USM}


ADAPTATION_TEXT = ("Each network fitted to each scan before reconstructing it (`nlosjax.adaptation.adapt` with"
                   " its defaults and the retroreflective forward model, nothing chosen on these scans):"
                   " intensity PSNR (dB), mean over the references, as trained → fitted, per scan and mean{detail};"
                   " last column the seconds per scan the fitted network took, fitting included:")
ALIGNED_TEXT = ("Each network after the second training stage on unlabelled measured inputs"
                " (`python -m experiments.studies.align`: the synthetic loss plus the MMD² of one layer's features to"
                " measured inputs, the layer named per fold below), one network per scan, trained on the *other*"
                " scans' inputs only: intensity PSNR (dB), mean over the references, as trained → aligned"
                " without that scan, per scan and mean{detail}; last column the seconds per scan:")


def aligned_lines(results, aligned: dict) -> list[str]:
  """:func:`adaptation_lines` for one :func:`aligned_run`, its workdir and lam per fold in the text."""
  lams = "; ".join(aligned.get("lam", [])) or "not recorded"
  return adaptation_lines(results, aligned, "aligned", ALIGNED_TEXT,
                          detail=f" (workdir `{aligned.get('workdir', '?')}`, lam and layer per fold: {lams})")


def adaptation_lines(results, adaptation, suffix: str = "adapted", text: str = ADAPTATION_TEXT,
                     detail: str = "") -> list[str]:
  """Each network as trained and as ``"<variant>|<suffix>"`` in ``adaptation``: per scan, then per reference.

  The first table: per scan (the mean over the references), the mean over the scans and
  how many scans went up; the second: against each full-scan reference, the mean over
  the same scans, as trained → ``suffix``. ``text`` heads the tables, with ``detail``
  put in its ``{detail}`` field.
  """
  if not adaptation:
    return []
  scenes = list(results["scenes"])
  lines = [text.format(detail=detail), "",
           "| network | input | " + " | ".join(scenes) + " | mean | scans up | s per scan |",
           "|---|---|" + "---|" * (len(scenes) + 3)]
  by_ref = ["", f"The same networks against each full-scan reference (intensity PSNR (dB), mean over the"
            f" scans above, as trained → {suffix}; a network is not scored against a reference it is"
            " not; each reference is one classic method on the full 64 × 64 scan):", "",
            "| network | input | " + " | ".join(f"vs {LABELS[r]} 64 × 64" for r in REFERENCES) + " |",
            "|---|---|" + "---|" * len(REFERENCES)]
  for v in [m for m in results["methods"] if f"{m}|{suffix}" in adaptation["methods"]]:
    for stride in results["strides"]:
      g = 64 // stride
      cells, before, after, secs = [], [], [], []
      ref_before, ref_after = {r: [] for r in REFERENCES}, {r: [] for r in REFERENCES}
      for sc in scenes:
        a = results["scenes"][sc]["scores"].get((v, stride))
        b = adaptation["scenes"].get(sc, {}).get("scores", {}).get((f"{v}|{suffix}", stride))
        if a is None or b is None:
          cells.append("–")
          continue
        cells.append(f"{a['psnr']:.2f} → {b['psnr']:.2f}")
        before.append(a["psnr"])
        after.append(b["psnr"])
        secs.append(b["time_s"])
        for r in REFERENCES:
          if r in a["vs"] and r in b["vs"]:
            ref_before[r].append(a["vs"][r]["psnr"])
            ref_after[r].append(b["vs"][r]["psnr"])
      mean = f"**{np.mean(before):.2f} → {np.mean(after):.2f}**" if before else "–"
      up = f"{sum(y > x for x, y in zip(before, after))} of {len(before)}" if before else "–"
      lines.append(f"| {LABELS[v]} | {g} × {g} | " + " | ".join(cells) + f" | {mean} | {up} | "
                   f"{np.median(secs) if secs else float('nan'):.1f} |")
      ref_cells = [f"{np.mean(ref_before[r]):.2f} → {np.mean(ref_after[r]):.2f}" if ref_before[r] else "–"
                   for r in REFERENCES]
      by_ref.append(f"| {LABELS[v]} | {g} × {g} | " + " | ".join(ref_cells) + " |")
  return lines + by_ref + [""]


def ablation_lines(results, ablation) -> list[str]:
  """Mean intensity PSNR / SSIM of each network as trained and with its residuals zeroed."""
  if not ablation:
    return []
  cols = list(ABLATIONS)
  lines = ["What the networks' learned residuals do on these scans: each network as trained, and with"
           " parts of it zeroed (" + "; ".join(f"*{c}*: {ABLATION_TEXT[c]}" for c in cols)
           + "; means over scenes of the mean over references, PSNR (dB) / SSIM):", "",
           "| network | input | as trained | " + " | ".join(cols) + " |",
           "|---|---|---|" + "---|" * len(cols)]

  def mean(res, m, stride):
    vals = over_scenes(res, m, stride)
    return (f"{np.mean([v['psnr'] for v in vals]):.2f} / {np.mean([v['ssim'] for v in vals]):.3f}"
            if vals else "–")
  for v in [m for m in results["methods"] if m not in UNTRAINED]:
    if not any(f"{v}|{c}" in ablation["methods"] for c in cols):
      continue
    for stride in results["strides"]:
      g = 64 // stride
      lines.append(f"| {LABELS[v]} | {g} × {g} | {mean(results, v, stride)} | "
                   + " | ".join(mean(ablation, f"{v}|{c}", stride) for c in cols) + " |")
  return lines + [""]
