"""The Markdown report ``tradeoff.md`` of the study's results: provenance, the Pareto front
and recommended settings, one table per knob, and the time-gating section.
"""

from __future__ import annotations

import datetime
import math

from experiments.configs import get_config
from experiments.studies.tradeoff.configs import CLASSIC, GOAL_HALVING, LABELS, LEARNING_RATE
from experiments.studies.tradeoff.pareto import learned_beats_classic, pareto_front, pareto_points, recommend
from nlosjax.variants import OURS, OURS_S


def _main_job_steps() -> int:
  """Training steps of the main job's default preset (the README's command 1)."""
  return int(get_config()["train"]["steps"])


def _ms(s: float) -> str:
  return f"{1e3 * s:.1f}" if s * 1e3 < 100 else f"{1e3 * s:.0f}"


def knob_table(rows: list[dict]) -> list[str]:
  lines = ["| configuration | ms / frame | range | compile s | XLA MiB | PSNR (dB) ↑ | SSIM ↑ |"
           " depth RMSE (m) ↓ | depth MAD (m) ↓ |",
           "|---|---|---|---|---|---|---|---|---|"]
  for r in rows:
    lo, hi = r.get("time_range", (r["time"], r["time"]))
    lines.append(f"| {r['label']} | {_ms(r['time'])} | {_ms(lo)}-{_ms(hi)} | {r['compile_s']:.1f} |"
                 f" {r['mem_mib']:.1f} |"
                 f" {r['psnr'][0]:.2f} ± {r['psnr'][1]:.2f} | {r['ssim'][0]:.3f} |"
                 f" {r['rmse'][0]:.3f} | {r['mad'][0]:.3f} |")
  return lines


def to_markdown(res: dict, cmd: str, machine: str, loads: tuple[str, str], *,
                gating: bool = True) -> str:
  """The Markdown report of :func:`run`'s results (``gating``: include the gating section)."""
  rows = res["configs"]
  pts = pareto_points(res)
  default = [p for p in pts if p["capture"] == "default"]
  front = pareto_front([p["time"] for p in default], [p["psnr"] for p in default])
  front_names = [p["name"] for p, f in zip(default, front) if f]
  rec = recommend(default)
  beats = learned_beats_classic(default)
  from experiments.provenance import git_commit
  by_name = {r["name"]: r for r in rows}
  (h, w), stride = res["grid"], res["stride"]
  full, sparse = f"{h} x {w}", f"{-(-h // stride)} x {-(-w // stride)}"   # the scan and the network's input
  out = [
      "# Speed and accuracy of every reconstruction knob",
      "",
      f"Produced by `{cmd}` on {datetime.date.today().isoformat()} ({res['wall_s']:.0f} s).",
      "",
      f"- Commit: {git_commit()}",
      f"- Machine: {machine}. Load average (1, 5, 15 min) before: {loads[0]}; after: {loads[1]}."
      + _load_remark(loads[0]) +
      f" Every time in this file comes from one phase in which all"
      f" {res['executables']} executables were called in turn, {res['rounds']} rounds after a"
      f" warm-up round ({res['timing_s']:.0f} s): the median is reported, and the `range` column"
      " gives the fastest and slowest round, the noise within this run. Between runs the load"
      " of the shared machine moves absolute times much more than that; ratios between rows of"
      " this file are the stable quantity.",
      f"- Data: test split of `{res['data']}`, {res['frames']} frames (8 sequences x middle frames"
      f" 1-6), {full} scan grid, {res['num_bins']} bins of"
      f" {res['bin_width'] * 1e12:.0f} ps, {res['wall_size']:g} m wall; objects at"
      f" {res['depth_range'][0]:g}-{res['depth_range'][1]:g} m.",
      f"- Learned configurations: trained by this benchmark, {res['steps']} AdamW steps of batch 4"
      f" each (the CPU preset's optimiser at peak learning rate {LEARNING_RATE:g}, with the cosine schedule"
      " over those steps, seed 0, the"
      f" main job's batches; the main job trains {_main_job_steps()} steps, so `Ours` here is not"
      " Table 1's unless the budgets match).",
      f"- Time: jitted pipeline `input -> (intensity, depth)`, batch {res['batch']}, per frame ="
      " median call / batch; compile = `.lower().compile()` (tracing, operator construction"
      " cached per Setup, XLA). XLA MiB = `memory_analysis()` temp + argument + output bytes"
      " (constants not counted; not the process RSS).",
      "- Accuracy: mean ± std over frames of intensity PSNR; means of SSIM, depth RMSE and MAD"
      " (background 0 m), against the ground truth, as Table 1. Classic methods read the"
      f" under-scanned input interpolated bilinearly to {full} (the paper's protocol)."
      + (" CSA, the iterative method made for under-scanned scans, reads the sparse scan itself"
         f" (a {full} grid masked to its {sparse} points) and counts here as a method without"
         " training (`classic`); its l1 weight and falloff were chosen in this run on"
         f" {res['csa_choice']['frames']} validation frames (see the method table)."
         if res.get("csa_choice") else ""),
      "",
      "## Pareto front and recommended settings",
      "",
      "![time per frame vs PSNR](tradeoff.png)",
      "",
      f"The front is taken over the configurations that read the same capture ({sparse} scan"
      " points, the stored exposure): different reconstructions of the same data. Scan-density"
      " and exposure points (hollow in the plot) change the capture, not the reconstruction,"
      " and are shown for reference.",
      "",
      "Pareto front (fastest first): " + ", ".join(
          f"{by_name[n]['label']} ({_ms(by_name[n]['time'])} ms, {by_name[n]['psnr'][0]:.2f} dB)"
          for n in sorted(front_names, key=lambda n: by_name[n]["time"])) + ".",
      "",
      "| goal | configuration | ms / frame | PSNR (dB) | depth RMSE (m) |",
      "|---|---|---|---|---|",
  ]
  for goal in ("fastest", "balanced", "best"):
    r = by_name[rec[goal]]
    out.append(f"| {goal} | {r['label']} | {_ms(r['time'])} | {r['psnr'][0]:.2f} |"
               f" {r['rmse'][0]:.3f} |")
  out += ["", "(fastest: least time on the front; balanced: the fastest front point within 1 dB"
          " of the best PSNR; best: highest PSNR.)", ""]
  best_classic = max((p for p in default if p["kind"] == "classic"), key=lambda p: p["psnr"])
  out.append("Learned configurations on the front that are faster than every classic"
             " configuration reaching their PSNR and more accurate than every faster classic one: "
             + (", ".join(by_name[n]["label"] for n in beats) if beats else "none")
             + f". Best classic configuration: {by_name[best_classic['name']]['label']}"
             f" ({best_classic['psnr']:.2f} dB, {_ms(best_classic['time'])} ms).")
  learned_pts = [p for p in default if p["kind"] == "learned"]
  if learned_pts:
    top = max(p["psnr"] for p in learned_pts)
    denser = sorted((p for p in pts if p["kind"] == "classic" and p["psnr"] >= top),
                    key=lambda p: p["time"])
    out.append("")
    out.append(f"Across captures, the classic configurations at or above the best learned PSNR"
               f" ({top:.2f} dB, {sparse} scan points) are: "
               + (", ".join(f"{p['label']} ({p['psnr']:.2f} dB, {_ms(p['time'])} ms)" for p in denser)
                  if denser else "none")
               + (" -- they read 4-16x more scan points than the networks." if denser else "."))
  out.append("")

  sections = [
      ("method", "Method (default capture)", None),
      ("density", f"Scan density (classic methods; the networks are trained for {sparse})",
       f"The {sparse} rows are those of the method table."),
      ("exposure", "Exposure (stored noise-free transients re-noised with `add_spad_noise`;"
       " x1 is a fresh draw at the stored exposure)", "Each exposure runs the default capture's"
       " executable on other data, so its time and compile columns are that executable's."),
      ("frames", "Frames (same budget)", None),
      ("model", "Model size (same budget; default: width 8, 1 ST-Mamba block, N = 4)", None),
      ("kernel", "Scan kernel and precision (default weights; `auto` = sequential on CPU)", None),
      ("gating", "Time gating on: a Setup depth range = the scenes' 0.5-1.5 m (off: the method"
       " table)", None),
  ]
  extra_rows = {"frames": [OURS_S, OURS], "model": [OURS], "kernel": [OURS]}
  for knob, title, note in sections:
    rs = [r for r in rows if r["knob"] == knob]
    if not rs:
      continue
    rs = [by_name[n] for n in extra_rows.get(knob, []) if n in by_name] + rs
    if knob == "density":
      rs = sorted(rs, key=lambda r: (CLASSIC.index(r["name"].split("@")[0]),
                                     int(r["setting"].split("x")[0])))
    out += [f"## {title}", ""] + knob_table(rs) + ([""] + [note] if note else []) + [""]
    if knob == "kernel":
      out += ["The default row (`Ours`) uses `auto`, which is `sequential` on CPU.", ""]
    if knob == "method" and res.get("csa_choice"):
      out += csa_choice_markdown(res["csa_choice"])
  if gating and res.get("gating"):
    out += gating_markdown(res)
  return "\n".join(out) + "\n"


def csa_choice_markdown(choice: dict) -> list[str]:
  """CSA's validation table: mean intensity PSNR per (falloff, l1 weight), the chosen one bold."""
  falloffs = list(dict.fromkeys(f for f, _, _ in choice["psnr"]))
  taus = list(dict.fromkeys(t for _, t, _ in choice["psnr"]))
  val = {(f, t): v for f, t, v in choice["psnr"]}
  chosen = tuple(choice["chosen"])
  out = [f"CSA's settings, chosen on {choice['frames']} validation frames (mean intensity PSNR, dB;"
         " the test split was not read):", "",
         "| falloff | " + " | ".join(f"tau_rel {t:g}" for t in taus) + " |",
         "|---|" + "---|" * len(taus)]
  for f in falloffs:
    out.append(f"| {f} | " + " | ".join(
        (f"**{val[(f, t)]:.2f}**" if (f, t) == chosen else f"{val[(f, t)]:.2f}") for t in taus) + " |")
  return out + [""]


def gating_markdown(res: dict) -> list[str]:
  """The time-gating section: times and ratios, accuracy inside the range, the stage profile."""
  from nlosjax.evaluation.report import METHOD_LABELS
  g, st = res["gating"], res["stages"]
  labels = list(next(iter(g.values())))
  halvings = [("full", "full/2"), ("R", "R/2"), ("R/2", "R/4")]
  if "R|a" in labels:
    halvings.append(("R|a", "R/2|a"))
  out = ["## Time gating by depth range", "",
         "A Setup depth range gates the time bins each method reads and crops the volume"
         " (`Setup.with_depth_range`); the networks keep their weights (`ModelConfig.with_setup`)."
         " Times are ms per frame (interleaved with every other executable, see the top).", ""]
  first = next(iter(g.values()))
  desc = []
  for lab in labels:
    r = first[lab]
    rng = _rng(r["range"]) + (f", aperture {r['aperture']:g} m" if r.get("aperture") else "")
    desc.append(f"`{lab}` = {rng} (depth bins {r['depth_bins'][0]}-{r['depth_bins'][1] - 1},"
                f" time bins {r['time_bins'][0]}-{r['time_bins'][1] - 1})")
  out += ["Ranges: " + "; ".join(desc) + ".", ""]
  out += ["| method | " + " | ".join(labels) + " | " +
          " | ".join(f"{a} / {b}" for a, b in halvings) + " |",
          "|---|" + "---|" * (len(labels) + len(halvings))]
  for method, rr in g.items():
    lab = LABELS.get(method) or METHOD_LABELS[method]
    out.append(f"| {lab} | " + " | ".join(_ms(rr[k]["time"]) for k in labels) + " | " +
               " | ".join(f"{rr[a]['time'] / rr[b]['time']:.2f}x" for a, b in halvings) + " |")
  lct, ours = g["lct"], g[OURS]
  r_lct, r_ours = lct["R"]["time"] / lct["R/2"]["time"], ours["R"]["time"] / ours["R/2"]["time"]
  f_lct = lct["full"]["time"] / lct["full/2"]["time"]
  f_ours = ours["full"]["time"] / ours["full/2"]["time"]
  with_ap = "R|a" in lct
  if with_ap:
    a_lct = lct["R|a"]["time"] / lct["R/2|a"]["time"]
    a_ours = ours["R|a"]["time"] / ours["R/2|a"]["time"]
  met = min(a_lct, a_ours) >= GOAL_HALVING if with_ap else min(r_lct, r_ours) >= GOAL_HALVING
  out += ["", f"**Goal: halving the depth range cuts the time of LCT and of the network by >="
          f" {GOAL_HALVING}x -- {'met' if met else 'not met'}"
          + (f" with an aperture of {lct['R|a']['aperture']:g} m" if with_ap else "") + ".**"
          + (f" With the aperture, R|a -> R/2|a: LCT {a_lct:.2f}x, Ours {a_ours:.2f}x." if with_ap
             else "")
          + f" Without it, halving the scenes' range R ="
          f" {_rng(lct['R']['range'])} to R/2 = {_rng(lct['R/2']['range'])}: LCT {r_lct:.2f}x,"
          f" Ours {r_ours:.2f}x. Halving the full range (0-{res['max_depth']:.3g} m ->"
          f" {_rng(lct['full/2']['range'])}): LCT {f_lct:.2f}x, Ours {f_ours:.2f}x.", ""]

  out += ["Accuracy inside the range, over the pixels whose true depth lies in it (object pixels"
          " only): depth RMSE (m) against the truth, gated / ungated reconstruction of the same"
          " pixels; missed = the share of those pixels reconstructed as background (depth < 0.1 m),"
          " gated / ungated; agree = mean |gated - ungated| depth over them (m). PSNR ="
          " whole-frame intensity PSNR (dB), ungated / gated to R (R holds every object).", "",
          "| method | " + " | ".join(f"depth RMSE {k}" for k in labels[1:]) + " | " +
          " | ".join(f"missed {k}" for k in labels[1:]) + " | " +
          " | ".join(f"agree {k}" for k in labels[1:]) + " | PSNR full / R |",
          "|---|" + "---|" * (3 * (len(labels) - 1) + 1)]
  for method, rr in g.items():
    lab = LABELS.get(method) or METHOD_LABELS[method]
    out.append(f"| {lab} | " + " | ".join(
        f"{rr[k]['rmse_gated']:.3f} / {rr[k]['rmse_ungated']:.3f}" for k in labels[1:]) + " | " +
        " | ".join(f"{rr[k]['missed_gated']:.2f} / {rr[k]['missed_ungated']:.2f}"
                   for k in labels[1:]) + " | " +
        " | ".join(f"{rr[k]['agreement']:.3f}" for k in labels[1:]) +
        f" | {rr['full']['psnr'][0]:.2f} / {rr['R']['psnr'][0]:.2f} |")

  B = res["batch"]
  out += ["", "### Where the time goes", "",
          "LCT split in three stages (`lct_stages`; ms per frame, timed side by side): `input` ="
          " time window -> v-resampling -> lateral FFTs of the Nv v-rows; `v-axis` = FFT of length"
          " Lv along v, Wiener filter, inverse FFT kept to Nu rows; `output` = inverse lateral FFTs"
          " of the Nu rows, u -> depth. Ours: the `volume` stage (feature extraction, physics layer,"
          " refinement) alone, and the `front` (extraction, ST-Mamba, cross ST-Mamba, spreading on"
          " the Tw-bin time window) = whole - volume.", "",
          "| range | LCT Nt / Nv / Lv / Nu | LCT input | v-axis | output | Ours Tw | Ours front |"
          " Ours volume |", "|---|---|---|---|---|---|---|---|"]
  for lab in labels:
    a, b = st["lct"][lab], st[OURS][lab]
    out.append(f"| {lab} | {a['nt']} / {a['nv']} / {a['lv']} / {a['nu']} | {_ms(a['input'] / B)} |"
               f" {_ms(a['v-axis'] / B)} | {_ms(a['output'] / B)} | {b['tw']} |"
               f" {_ms(b['front'] / B)} | {_ms(b['volume'] / B)} |")
  a, b = st["lct"]["R"], st["lct"]["R/2"]
  c, d = st[OURS]["R"], st[OURS]["R/2"]
  out += ["", f"From R to R/2 the LCT stages get {a['input'] / b['input']:.2f}x (input),"
          f" {a['v-axis'] / b['v-axis']:.2f}x (v-axis) and {a['output'] / b['output']:.2f}x (output)"
          f" faster; the network's front {c['front'] / max(d['front'], 1e-12):.2f}x and its volume"
          f" stage {c['volume'] / d['volume']:.2f}x.", ""]
  wall, zmax = res["wall_size"], res["max_depth"]
  rb = first["R"]
  z_far = first["R"]["range"][1]
  diag = math.sqrt(2.0) * wall
  out += ["**Why the time does not halve with the range.** A gated method must read every time"
          " bin that can hold a return from the range: from `z_min` straight ahead up to the far"
          f" edge seen from a scan point one wall diagonal ({diag:.2f} m) away, at a distance of"
          f" hypot({z_far:g}, {diag:.2f}) = {math.hypot(z_far, diag):.2f} m, beyond the histogram's"
          f" reach of {zmax:.2f} m (T c dt / 2). So every window here ends at the last bin (R: time bins"
          f" {rb['time_bins'][0]}-{rb['time_bins'][1] - 1}); halving the range only moves its"
          " start. What scales with the range is the depth side: LCT's output stage (Nu u-rows)"
          " and half of its v-axis FFT (Lv >= Nv + Nu - 1), the network's volume stage (physics"
          " layer and refinement on the depth bins). What does not: LCT's v-resampling and lateral"
          " FFTs of Nv ~ T - t0^2 / T rows, and the network's front on the Tw-bin window. Time ~"
          " a + b Z with a large a. A range makes a real difference against no range at all (the"
          " `full` column; f-k excepted) but not between two ranges of this geometry. What"
          " changes it: `Setup.aperture` bounds the lateral reach (voxel-to-scan-point offsets"
          " up to rho; cone paths beyond it are not modelled), so the window ends at"
          " hypot(z_max, rho) and Nv falls with the range (the `R|a` columns); its price is the"
          " oblique returns it ignores, measured in the accuracy table above.", ""]
  return out


def _load_remark(load_before) -> str:
  """A sentence on what the load average before the run means for the times."""
  try:
    one_minute = float(str(load_before).split(",")[0])
  except ValueError:
    return ""
  if one_minute < 1.5:
    return " The machine was otherwise quiet (1-minute load below 1.5 on 2 cores)."
  return (" Other jobs shared the cores while this ran, so times are upper bounds for an idle"
          " machine.")


def _rng(r) -> str:
  return "no range" if r is None else f"{r[0]:.3g}-{r[1]:.3g} m"
