"""The Markdown report of :mod:`benchmarks.physics`: tables, goals and the machine lines."""

from __future__ import annotations

import datetime
import math
import pathlib
import platform

import numpy as np

from benchmarks.physics.cases import TWIN_OPTIONS
from benchmarks.physics.scene import BACKGROUND, BIN_WIDTH, SCENE_POINTS, SIGNAL_PHOTONS, WALL_SIZE
from experiments import provenance as _machine_facts

DEFAULT_OUT = pathlib.Path(__file__).resolve().parent.parent / "results" / "physics.md"
GOAL_SPEEDUP = 1.0   # JAX at least as fast as the twin of the same variant ...
GOAL_FLOOR = 1.3     # ... and at most this multiple of its FFT floor ...
GOAL_SIZES = (64, 128)  # ... at these scan sizes
MB = 1024.0 ** 2


def ncc(a: np.ndarray, b: np.ndarray) -> float:
  """Normalised (zero-mean) cross-correlation of two images; nan if either is flat."""
  a = np.asarray(a, np.float64).ravel()
  b = np.asarray(b, np.float64).ravel()
  if a.shape != b.shape:
    return float("nan")
  a = a - a.mean()
  b = b - b.mean()
  denom = math.sqrt(float(a @ a) * float(b @ b))
  return float(a @ b) / denom if denom > 0 else float("nan")


def machine_info(jax_status: str) -> list[str]:
  import scipy

  cores = _machine_facts.usable_cores()
  versions = [f"Python {platform.python_version()}", f"numpy {np.__version__}",
              f"scipy {scipy.__version__}"]
  try:
    import jax
    import jaxlib

    versions[1:1] = [f"jax {jax.__version__}", f"jaxlib {jaxlib.__version__}"]
  except ImportError:
    versions.append("jax not installed")
  return [
      f"- Date: {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}",
      f"- Commit: {_machine_facts.git_commit()}",
      f"- Machine: {_machine_facts.machine_text()}",
      f"- Versions: {', '.join(versions)}",
      f"- JAX side: {jax_status}",
      f"- Load average (1, 5, 15 min) when written: {_machine_facts.load_average(', ')}; above"
      f" {cores} the cores were shared with other jobs and the times are upper bounds (the"
      " speed-ups compare the two sides measured in turn, case by case)",
  ]


def fmt(value, spec: str = ".3f", missing: str = "-") -> str:
  if value is None or (isinstance(value, float) and not math.isfinite(value)):
    return missing
  return format(value, spec)


def cell(side: dict | None, key: str, spec: str = ".3f", scale: float = 1.0) -> str:
  if side is None:
    return "n/a"
  if side.get("status") != "ok":
    return side["status"] if key.endswith("run_s") else "-"
  value = side.get(key)
  return fmt(None if value is None else value * scale, spec)


def format_table(rows: list[dict], with_jax: bool) -> list[str]:
  head = ["method", "N", "T"]
  if with_jax:
    head += ["JAX compile s", "JAX run s"]
  head += ["NumPy build s", "NumPy run s"]
  if with_jax:
    head += ["speed-up (NumPy/JAX)", "FFT floor s", "JAX / floor", "JAX peak MB"]
  head += ["NumPy peak MB"]
  if with_jax:
    head += ["MIP NCC"]
  lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
  for r in rows:
    j, p = r.get("jax"), r["numpy"]
    cells = [r["method"], f"{r['n']}²", str(r["bins"])]
    if with_jax:
      cells += [cell(j, "compile_s"), cell(j, "run_s", ".4f")]
    cells += [cell(p, "build_s"), cell(p, "run_s", ".4f")]
    if with_jax:
      cells += [fmt(r.get("speedup"), ".2f") + ("×" if r.get("speedup") else ""),
                cell(j, "floor_s", ".4f"),
                fmt(r.get("over_floor"), ".2f") + ("×" if r.get("over_floor") else ""),
                cell(j, "peak_bytes", ".1f", 1 / MB)]
    cells += [cell(p, "peak_bytes", ".1f", 1 / MB)]
    if with_jax:
      cells += [fmt(r.get("ncc"), ".3f")]
    lines.append("| " + " | ".join(cells) + " |")
  return lines


def format_details(rows: list[dict], with_jax: bool) -> list[str]:
  head = ["method", "N", "NumPy first run s", "NumPy repeats", "NumPy operators MB",
          "NumPy process max RSS MB"]
  if with_jax:
    head += ["JAX first call s", "JAX repeats", "JAX process max RSS MB"]
  lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
  for r in rows:
    j, p = r.get("jax"), r["numpy"]
    ok_p = p.get("status") == "ok"
    cells = [r["method"], f"{r['n']}²",
             fmt(p.get("first_s")) if ok_p else "-",
             str(len(p["runs"])) if ok_p else "-",
             fmt(p.get("ops_bytes", 0) / MB, ".1f") if ok_p else "-",
             fmt(p.get("rss_mb"), ".0f") if ok_p else "-"]
    if with_jax:
      ok_j = j is not None and j.get("status") == "ok"
      cells += [fmt(j.get("first_s")) if ok_j else "-",
                str(len(j["runs"])) if ok_j else "-",
                fmt(j.get("rss_mb"), ".0f") if ok_j else "-"]
    lines.append("| " + " | ".join(cells) + " |")
  return lines


def goal_summary(rows: list[dict]) -> list[str]:
  """One line per goal size: which methods meet both goals, and the measured ratios of those that miss."""
  lines = []
  for n in GOAL_SIZES:
    case = [r for r in rows if r["n"] == n]
    if not case:
      continue
    met, missed = [], []
    for r in case:
      sp, fl = r.get("speedup"), r.get("over_floor")
      if sp is None or fl is None:
        missed.append(f"{r['method']} (no result)")
      elif sp >= GOAL_SPEEDUP and fl <= GOAL_FLOOR:
        met.append(r["method"])
      else:
        missed.append(f"{r['method']} ({fl:.2f}× floor, {sp:.2f}× twin)")
    lines.append(f"- {n}²: met by {', '.join(met) or 'none'}"
                 + (f"; missed by {', '.join(missed)}" if missed else ""))
  return lines


def write_report(path: pathlib.Path | None, command: str, args, rows: list[dict],
                 with_jax: bool, jax_status: str, peak_notes: list[str],
                 study: dict | None = None) -> str:
  lines = [
      "# Classic reconstructions: JAX vs NumPy/SciPy",
      "",
      f"Produced by `{command}`.",
      "",
      *machine_info(jax_status),
      f"- Scene: {len(SCENE_POINTS)} point scatterers (1/r^4), {SIGNAL_PHOTONS:g} signal photons"
      f" per scan point, {BACKGROUND:g} background counts per bin, Poisson noise; wall"
      f" {WALL_SIZE:g} m, {BIN_WIDTH * 1e12:g} ps bins, {args.bins} bins, N x N scan points.",
      f"- Repeats: median of {args.repeats} warm runs after one warm-up; a step longer than"
      f" {args.time_limit:g} s is recorded as a timeout.",
      "- Options: every method at nlosjax's defaults (FBP, LCT, f-k and phasor:"
      " `variant=\"public\"`, the algorithm the twin ports); the twin gets the same wavelet"
      f" where its default differs ({TWIN_OPTIONS}).",
      "",
      "Columns: JAX compile = `jax.jit(...).lower(x).compile()`; JAX run = compiled call +"
      " `block_until_ready`; NumPy build = the twin's operators (PSF spectrum, resampling"
      " matrices, Stolt tables, wavelets); NumPy run = `numpy_twins.<method>(x, ops)`;"
      " speed-up = NumPy run / JAX run; FFT floor = the method's forward and inverse FFTs"
      " alone, jitted, on the same input (`fft_floor`), timed alternately with the JAX run;"
      " JAX / floor = JAX run / FFT floor; JAX peak = temp + argument + output bytes of"
      " `compiled.memory_analysis()` (constants folded into the executable, such as"
      " prebuilt operators, are not counted); NumPy peak = `tracemalloc` peak during one run"
      " (operators built beforehand are not counted; their size is in the details table);"
      " MIP NCC = normalised cross-correlation of the two max-intensity projections.",
      "",
      *format_table(rows, with_jax),
      "",
  ]
  if with_jax:
    goal = goal_summary(rows)
    if goal:
      lines += [f"Goals (JAX run ≤ {GOAL_FLOOR:g}× its FFT floor and ≥ {GOAL_SPEEDUP:g}× the"
                f" twin's speed, at {' and '.join(f'{g}²' for g in GOAL_SIZES)}):", "", *goal, ""]
  if study is not None:
    st = study["setup"]
    lines += [
        "## Operator variants: what the refined operators buy",
        "",
        "`variant=\"public\"` (the default) is the public code's operators, so a user's"
        " `snr` gives the public image (`tests/test_real_data.py`: max-projection NCC ≥ 0.95"
        " against the NumPy twins on both shipped scans down to 0.5 % of their photons)."
        " `variant=\"refined\"` is ours: the cone averaged over each voxel's footprint on the"
        " true scan spacing `wall/(N-1)`, linear convolution, gated time, `oversample`; f-k's"
        " refined variant only changes the spacing. Points:"
        f" {study['num_points']} single scatterers, each alone, noise-free (the brute-force"
        f" renderer above), {st.grid[0]} × {st.grid[1]} scan points, {st.wall_size:g} m wall,"
        f" {st.num_bins} bins of {st.bin_width * 1e12:g} ps, depths 0.5-1.5 m; error of the"
        " volume's peak against the true (fractional) depth bin and the nearest scan point."
        " Measured scans: full counts, median of 3 warm jitted runs, and the max-projection"
        " NCC against the public variant's image (they have no ground truth, so there the"
        " table shows cost and how far the refined image moves, not accuracy).",
        "",
        *format_variant_study(study),
        "",
    ]
  lines += ["Details:", "", *format_details(rows, with_jax), ""]
  if peak_notes:
    lines += ["Notes:", "", *[f"- {note}" for note in peak_notes], ""]
  text = "\n".join(lines)
  if path is not None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
  return text


def format_variant_study(study: dict) -> list[str]:
  names = [s["name"] for s in study["rows"][0]["scans"]]
  head = ["method", "options", "depth bias (bins)", "depth MAE (bins)", "depth max (bins)",
          "lateral error (scan points)"]
  for name in names:
    head += [f"{name} run s", f"{name} MIP NCC vs public"]
  lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
  for r in study["rows"]:
    opts = ", ".join(f"{k}={v}" for k, v in r["options"].items())
    cells = [r["method"], opts, f"{r['depth_bias']:+.2f}", f"{r['depth_mae']:.2f}",
             f"{r['depth_max']:.2f}", f"{r['lateral_mean']:.2f}"]
    for sc in r["scans"]:
      cells += [f"{sc['run_s']:.3f}", fmt(sc["ncc_public"], ".3f")]
    lines.append("| " + " | ".join(cells) + " |")
  return lines
