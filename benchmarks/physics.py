"""Benchmark the classic reconstructions: jitted JAX against their NumPy/SciPy twins.

    python -m benchmarks.physics [--sizes 32 64 128] [--bins 512] [--methods fbp lct ...]
                                 [--repeats 3] [--out benchmarks/results/physics.md] [--quick]

For every scan size ``N`` and method, one synthetic transient (a few point
scatterers, Poisson noise; 2 m wall, ``N x N`` scan points, ``--bins`` bins of
32 ps) is reconstructed in the same run by

* JAX: ``jax.jit(lambda x: nlosjax.physics.reconstruct(x, setup, method))``.
  Compile time is ``.lower(x).compile()``; run time the median of
  ``--repeats`` warm calls (after one warm-up call), each ended by
  ``block_until_ready``; peak memory from ``compiled.memory_analysis()``
  (temp + argument + output buffers);
* the NumPy/SciPy twin (``experiments/numpy_twins.py``, the public algorithm):
  operator build time, then the median of ``--repeats`` runs after one
  warm-up run, ``scipy.fft`` on all cores; peak memory is the ``tracemalloc``
  peak during one more run (allocations of the run only, operators excluded).

Beside each JAX run, in the same child process and on the same input, the
method's **FFT floor**: a jitted function doing only the forward and inverse
FFTs of the sizes the method needs (:func:`fft_floor`), timed the same way.
The goals are JAX run <= 1.3x its floor and >= 1x the twin (the same
algorithm variant: the library's defaults are the public operators).

A second table, the **variant study** (``--no-variants`` skips it), compares
``variant="public"`` with ``variant="refined"`` (and the refined LCT grid at
``oversample=2``): depth and lateral errors of the peak on point scatterers
(the brute-force renderer below, noise-free), and on the two shipped measured
scans the run time and the agreement of the two variants' images.

Each side of each case runs in a fresh child process, so a case that runs out
of memory or takes longer than ``--time-limit`` seconds in one step is
recorded as such instead of stopping the benchmark. The two volumes'
max-intensity projections are compared by normalised cross-correlation as a
sanity check. The JAX columns are left out when ``nlosjax.physics.reconstruct``
cannot be imported.

The Markdown table goes to ``--out`` (``benchmarks/results/physics.md`` by
default; ``--quick`` -- 32^2 scan points, 128 bins, a smoke test -- only
prints unless ``--out`` is given).
"""

from __future__ import annotations

import argparse
import datetime
import math
import multiprocessing
import pathlib
import platform
import resource
import statistics
import sys
import time
import traceback
import tracemalloc

import numpy as np

from experiments import numpy_twins
from experiments import provenance as _machine_facts
from nlosjax.physics.forward import render_points
from nlosjax.physics.setup import Setup

DEFAULT_OUT = pathlib.Path(__file__).resolve().parent / "results" / "physics.md"
WALL_SIZE = 2.0      # m
BIN_WIDTH = 32e-12   # s
GOAL_SPEEDUP = 1.0   # JAX at least as fast as the twin of the same variant ...
GOAL_FLOOR = 1.3     # ... and at most this multiple of its FFT floor ...
GOAL_SIZES = (64, 128)  # ... at these scan sizes
MB = 1024.0 ** 2

# The synthetic scene: (x, y) as fractions of the half wall, depth as a
# fraction of the deepest bin, albedo.
SCENE_POINTS = (
    (-0.45, -0.30, 0.35, 1.0),
    (0.35, 0.20, 0.45, 1.0),
    (0.00, 0.50, 0.55, 0.8),
    (-0.15, 0.05, 0.30, 0.6),
    (0.50, -0.45, 0.50, 1.0),
)
SIGNAL_PHOTONS = 200.0  # mean signal photons per scan point
BACKGROUND = 0.02       # mean background counts per bin


# ------------------------------------------------------------------- scene
def make_setup(n: int, bins: int) -> Setup:
  """The benchmark capture: 2 m wall, ``n x n`` scan points, ``bins`` bins of 32 ps."""
  return Setup(wall_size=WALL_SIZE, grid=(n, n), bin_width=BIN_WIDTH, num_bins=bins)


def synthetic_transient(setup: Setup, seed: int = 0) -> np.ndarray:
  """Float32 ``[T, H, W]`` photon counts of :data:`SCENE_POINTS` with Poisson noise."""
  half, depth = setup.wall_size / 2.0, setup.max_depth
  pts = np.array([(x * half, y * half, z * depth) for x, y, z, _ in SCENE_POINTS])
  albedo = np.array([a for *_, a in SCENE_POINTS])
  clean = render_points(pts, albedo, setup)
  clean *= SIGNAL_PHOTONS * setup.height * setup.width / max(clean.sum(), 1e-30)
  rng = np.random.default_rng(seed)
  return rng.poisson(clean + BACKGROUND).astype(np.float32)


# -------------------------------------------------------------- FFT floor
def fft_floor(method: str, setup: Setup):
  """A jittable ``x [T, H, W] -> array`` doing only the FFTs ``method`` needs, at their sizes.

  * ``lct``, ``fbp``: ``rfftn`` and ``irfftn`` of the padded ``(2T, 2H, 2W)`` volume
    (the public algorithm's box);
  * ``phasor``: the time convolution with the wavelet (complex FFT pair along
    ``t``) and the box's FFT pair for its real and imaginary parts;
  * ``fk``: ``rfft`` along ``t`` (length ``2T``), ``fft2`` on ``(2H, 2W)``, and
    back (``ifft2``, ``ifft``);
  * ``rsd``: ``rfft`` along ``t`` (the wall fields' DTFT), ``fft2`` of the ``K``
    wall fields on ``(2H, 2W)``, ``ifft2`` of the NUFFT grid's rows, ``ifft`` along
    its ``M`` cells (sizes from the plan).
  """
  import jax.numpy as jnp

  T, (H, W) = setup.num_bins, setup.grid
  box = (2 * T, 2 * H, 2 * W)

  def box_pair(v):
    return jnp.fft.irfftn(jnp.fft.rfftn(v, s=box), s=box)[:T, :H, :W]

  if method in ("lct", "fbp"):
    return box_pair
  if method == "phasor":
    from nlosjax.physics.wavelet import public_wavelet
    n = T + public_wavelet(setup).num_samples - 1

    def phasor_floor(v):
      field = jnp.fft.ifft(jnp.fft.fft(v, n=n, axis=0), axis=0)[:T]
      return box_pair(field.real) + box_pair(field.imag)
    return phasor_floor
  if method == "fk":
    def fk_floor(v):
      spec = jnp.fft.fft2(jnp.fft.rfft(v, n=2 * T, axis=0), s=(2 * H, 2 * W))
      return jnp.fft.ifft(jnp.fft.ifft2(spec)[:, :H, :W], n=2 * T, axis=0)[:T]
    return fk_floor
  if method == "rsd":
    import importlib
    recon = importlib.import_module("nlosjax.physics.reconstruct")   # the module, not the function
    plan = recon._rsd_plan(setup, 3.0, 2.0, 0.1, jnp.float32)
    k, rows, m = plan.bins.shape[0], plan.num_rows, plan.fft_len

    def rsd_floor(v):
      spec = jnp.fft.rfft(jnp.moveaxis(v, 0, -1), axis=-1)[..., :k]        # the wall fields' DTFT
      fields = jnp.fft.fft2(jnp.moveaxis(spec, -1, 0), s=(2 * H, 2 * W))
      grid = jnp.resize(fields, (rows, 2 * H, 2 * W))
      g = jnp.fft.ifft2(grid)[:, :H, :W].reshape(rows, H * W)
      return jnp.fft.ifft(g.T, n=m, axis=-1)
    return rsd_floor
  raise ValueError(f"unknown method {method!r}")


# ------------------------------------------------------------- child work
def _max_rss_mb() -> float:
  return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def _repeats_within(first_s: float, repeats: int, time_limit: float) -> int:
  """At least one repeat; fewer than asked when they would exceed the time limit."""
  if first_s <= 0:
    return repeats
  return max(1, min(repeats, int(time_limit // first_s)))


def _jax_worker(conn, method: str, n: int, bins: int, repeats: int, seed: int,
                time_limit: float) -> None:
  try:
    import jax

    from nlosjax.physics import reconstruct

    setup = make_setup(n, bins)
    x = jax.device_put(synthetic_transient(setup, seed))
    x.block_until_ready()
    fn = jax.jit(lambda v: reconstruct(v, setup, method))
    conn.send(("phase", "compile"))
    t0 = time.perf_counter()
    compiled = fn.lower(x).compile()
    compile_s = time.perf_counter() - t0
    peak_bytes, peak_note = None, ""
    try:
      stats = compiled.memory_analysis()
      if stats is None:
        peak_note = "memory_analysis() returned None"
      else:
        peak_bytes = int(stats.temp_size_in_bytes + stats.argument_size_in_bytes
                         + stats.output_size_in_bytes)
    except Exception as e:  # noqa: BLE001 - not every backend implements it
      peak_note = f"memory_analysis() unavailable: {type(e).__name__}: {e}"
    conn.send(("phase", "warm-up run"))
    t0 = time.perf_counter()
    out = compiled(x)
    out.block_until_ready()
    first_s = time.perf_counter() - t0
    vol = np.asarray(out)
    mip = vol.max(axis=0).astype(np.float32)
    del out, vol
    n_rep = _repeats_within(first_s, repeats, time_limit)
    floor = jax.jit(fft_floor(method, setup)).lower(x).compile()
    jax.block_until_ready(floor(x))
    times, floor_times = [], []
    for i in range(n_rep):
      # The method and its floor alternate, so both see the same machine load.
      conn.send(("phase", f"run {i + 1}/{n_rep}"))
      t0 = time.perf_counter()
      compiled(x).block_until_ready()
      times.append(time.perf_counter() - t0)
      t0 = time.perf_counter()
      jax.block_until_ready(floor(x))
      floor_times.append(time.perf_counter() - t0)
    conn.send(("result", {
        "status": "ok", "compile_s": compile_s, "first_s": first_s,
        "run_s": statistics.median(times), "runs": times,
        "floor_s": statistics.median(floor_times), "peak_bytes": peak_bytes,
        "peak_note": peak_note, "mip": mip, "rss_mb": _max_rss_mb(),
        "device": str(jax.devices()[0]),
    }))
  except MemoryError:
    conn.send(("result", {"status": "out of memory"}))
  except Exception as e:  # noqa: BLE001 - reported in the table
    oom = "RESOURCE_EXHAUSTED" in str(e) or "out of memory" in str(e).lower()
    conn.send(("result", {
        "status": "out of memory" if oom else f"error: {type(e).__name__}: {_first_line(e)}",
        "traceback": traceback.format_exc()}))


def _ops_bytes(ops) -> int:
  """Bytes held by the arrays (dense and sparse) of a twin's operators."""
  total = 0
  for value in vars(ops).values():
    if isinstance(value, np.ndarray):
      total += value.nbytes
    elif hasattr(value, "data") and hasattr(value, "indices") and hasattr(value, "indptr"):
      total += value.data.nbytes + value.indices.nbytes + value.indptr.nbytes
  return total


# The twin's options that differ from its own defaults, so that both sides run
# the same method: nlosjax's RSD defaults to a 3-cycle wavelet (5 in the twin).
TWIN_OPTIONS = {"rsd": {"cycles": 3.0}}


def _numpy_worker(conn, method: str, n: int, bins: int, repeats: int, seed: int,
                  time_limit: float) -> None:
  try:
    setup = make_setup(n, bins)
    x = synthetic_transient(setup, seed)
    conn.send(("phase", "build"))
    t0 = time.perf_counter()
    ops = numpy_twins.build(setup, method, **TWIN_OPTIONS.get(method, {}))
    build_s = time.perf_counter() - t0
    conn.send(("phase", "warm-up run"))
    t0 = time.perf_counter()
    vol = numpy_twins.run(x, method, ops)
    first_s = time.perf_counter() - t0
    mip = vol.max(axis=0).astype(np.float32)
    del vol
    n_rep = _repeats_within(first_s, repeats, time_limit)
    times = []
    for i in range(n_rep):
      conn.send(("phase", f"run {i + 1}/{n_rep}"))
      t0 = time.perf_counter()
      numpy_twins.run(x, method, ops)
      times.append(time.perf_counter() - t0)
    conn.send(("phase", "tracemalloc run"))
    tracemalloc.start()
    tracemalloc.reset_peak()
    numpy_twins.run(x, method, ops)
    peak_bytes = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    conn.send(("result", {
        "status": "ok", "build_s": build_s, "first_s": first_s,
        "run_s": statistics.median(times), "runs": times, "peak_bytes": int(peak_bytes),
        "ops_bytes": _ops_bytes(ops), "mip": mip, "rss_mb": _max_rss_mb(),
    }))
  except MemoryError:
    conn.send(("result", {"status": "out of memory"}))
  except Exception as e:  # noqa: BLE001 - reported in the table
    conn.send(("result", {"status": f"error: {type(e).__name__}: {_first_line(e)}",
                          "traceback": traceback.format_exc()}))


def _first_line(e: BaseException, limit: int = 120) -> str:
  line = str(e).strip().splitlines()[0] if str(e).strip() else ""
  return line[:limit]


def run_case(worker, method: str, n: int, bins: int, repeats: int, seed: int,
             time_limit: float) -> dict:
  """Run one side of a case in a fresh process; never raises.

  The child reports each step; if a step takes more than ``time_limit``
  seconds the child is killed and the case recorded as timed out. A child
  that dies (e.g. killed by the kernel for memory) is recorded too.
  """
  ctx = multiprocessing.get_context("spawn")
  parent_conn, child_conn = ctx.Pipe(duplex=False)
  proc = ctx.Process(target=worker, args=(child_conn, method, n, bins, repeats, seed, time_limit),
                     daemon=True)
  proc.start()
  child_conn.close()
  phase = "start-up"
  result = None
  try:
    while True:
      if not parent_conn.poll(time_limit):
        result = {"status": f"timeout (> {time_limit:.0f} s in {phase})"}
        break
      try:
        kind, payload = parent_conn.recv()
      except EOFError:
        proc.join(5)
        code = proc.exitcode
        why = "killed, likely out of memory" if code in (-9, 137) else f"exit code {code}"
        result = {"status": f"crashed in {phase} ({why})"}
        break
      if kind == "phase":
        phase = payload
      else:
        result = payload
        break
  finally:
    if proc.is_alive():
      proc.join(10)
    if proc.is_alive():
      proc.kill()
      proc.join()
    parent_conn.close()
  return result


# ---------------------------------------------------------- variant study
#: ``(method, options)`` rows of the variant study.
VARIANT_ROWS = (
    ("fbp", {"variant": "public"}), ("fbp", {"variant": "refined"}),
    ("lct", {"variant": "public"}), ("lct", {"variant": "refined"}),
    ("lct", {"variant": "refined", "oversample": 2}),
    ("fk", {"variant": "public"}), ("fk", {"variant": "refined"}),
    ("phasor", {"variant": "public"}), ("phasor", {"variant": "refined"}),
)
#: The point-scatterer capture of the study: 16 x 16 scan points on a 2 m wall, 512 x 32 ps.
POINT_SETUP = dict(wall_size=2.0, grid=(16, 16), bin_width=32e-12, num_bins=512)


def _peak(vol: np.ndarray) -> tuple[int, int, int]:
  return tuple(int(i) for i in np.unravel_index(int(np.argmax(vol)), vol.shape))


def variant_study(num_points: int = 16, seed: int = 0, repeats: int = 3) -> dict:
  """Point-scatterer errors and measured-scan times of every row of :data:`VARIANT_ROWS`.

  Points: ``num_points`` single scatterers, lateral position uniform in the
  central 70 % of the wall, depth uniform in 0.5-1.5 m, each rendered alone
  (noise-free, :func:`render_points`); the error is the volume's peak against
  the true depth bin (fractional) and the nearest scan point. Measured scans:
  the two shipped ones at full counts, median warm time of ``repeats`` runs and
  the max-projection NCC against the public variant's.
  """
  import jax

  from nlosjax.data import io
  from nlosjax.physics import reconstruct

  setup = Setup(**POINT_SETUP)
  rng = np.random.default_rng(seed)
  half = 0.35 * setup.wall_size
  pts = np.stack([rng.uniform(-half, half, num_points), rng.uniform(-half, half, num_points),
                  rng.uniform(0.5, 1.5, num_points)], axis=1)
  transients = np.stack([render_points(p[None], np.ones(1), setup) for p in pts]).astype(np.float32)
  true_k = pts[:, 2] / setup.depth_bin_length
  true_i = np.array([np.argmin(np.abs(setup.scan_y - p[1])) for p in pts])
  true_j = np.array([np.argmin(np.abs(setup.scan_x - p[0])) for p in pts])
  scans = [io.load_measurement(io.shipped_scan_path(name)) for name in io.SHIPPED_SCAN_NAMES]
  rows, public_mips = [], {}
  for method, opts in VARIANT_ROWS:
    vols = np.asarray(reconstruct(transients, setup, method, **opts))
    peaks = np.array([_peak(v) for v in vols])
    depth_err = peaks[:, 0] - true_k
    lateral = np.abs(peaks[:, 1] - true_i) + np.abs(peaks[:, 2] - true_j)
    row = {"method": method, "options": opts, "depth_bias": float(depth_err.mean()),
           "depth_mae": float(np.abs(depth_err).mean()), "depth_max": float(np.abs(depth_err).max()),
           "lateral_mean": float(lateral.mean()), "scans": []}
    for (transient, capture), name in zip(scans, io.SHIPPED_SCAN_NAMES):
      fn = jax.jit(lambda v, c=capture: reconstruct(v, c, method, **opts))
      x = jax.device_put(transient)
      mip = np.asarray(fn(x)).max(0)
      times = []
      for _ in range(repeats):
        t0 = time.perf_counter()
        fn(x).block_until_ready()
        times.append(time.perf_counter() - t0)
      if opts.get("variant") == "public":
        public_mips[(method, name)] = mip
      ref = public_mips.get((method, name))
      row["scans"].append({"name": name, "run_s": statistics.median(times),
                           "ncc_public": ncc(mip, ref) if ref is not None else None})
    rows.append(row)
  return {"rows": rows, "num_points": num_points, "setup": setup}


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
      cells += [f"{sc['run_s']:.3f}", _fmt(sc["ncc_public"], ".3f")]
    lines.append("| " + " | ".join(cells) + " |")
  return lines


# ------------------------------------------------------------- reporting
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
      _machine_facts.code_line(),
      f"- Machine: {_machine_facts.machine_text()}",
      f"- Versions: {', '.join(versions)}",
      f"- JAX side: {jax_status}",
      f"- Load average (1, 5, 15 min) when written: {_machine_facts.load_average(', ')}; above"
      f" {cores} the cores were shared with other jobs and the times are upper bounds (the"
      " speed-ups compare the two sides measured in turn, case by case)",
  ]


def _fmt(value, spec: str = ".3f", missing: str = "-") -> str:
  if value is None or (isinstance(value, float) and not math.isfinite(value)):
    return missing
  return format(value, spec)


def _cell(side: dict | None, key: str, spec: str = ".3f", scale: float = 1.0) -> str:
  if side is None:
    return "n/a"
  if side.get("status") != "ok":
    return side["status"] if key.endswith("run_s") else "-"
  value = side.get(key)
  return _fmt(None if value is None else value * scale, spec)


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
      cells += [_cell(j, "compile_s"), _cell(j, "run_s", ".4f")]
    cells += [_cell(p, "build_s"), _cell(p, "run_s", ".4f")]
    if with_jax:
      cells += [_fmt(r.get("speedup"), ".2f") + ("×" if r.get("speedup") else ""),
                _cell(j, "floor_s", ".4f"),
                _fmt(r.get("over_floor"), ".2f") + ("×" if r.get("over_floor") else ""),
                _cell(j, "peak_bytes", ".1f", 1 / MB)]
    cells += [_cell(p, "peak_bytes", ".1f", 1 / MB)]
    if with_jax:
      cells += [_fmt(r.get("ncc"), ".3f")]
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
             _fmt(p.get("first_s")) if ok_p else "-",
             str(len(p["runs"])) if ok_p else "-",
             _fmt(p.get("ops_bytes", 0) / MB, ".1f") if ok_p else "-",
             _fmt(p.get("rss_mb"), ".0f") if ok_p else "-"]
    if with_jax:
      ok_j = j is not None and j.get("status") == "ok"
      cells += [_fmt(j.get("first_s")) if ok_j else "-",
                str(len(j["runs"])) if ok_j else "-",
                _fmt(j.get("rss_mb"), ".0f") if ok_j else "-"]
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


# ------------------------------------------------------------------- main
def _jax_available() -> tuple[bool, str]:
  try:
    from nlosjax.physics import reconstruct  # noqa: F401
  except Exception as e:  # noqa: BLE001 - any import failure means: skip JAX
    return False, f"skipped: `from nlosjax.physics import reconstruct` failed ({type(e).__name__}: {_first_line(e)})"
  import jax

  return True, f"`nlosjax.physics.reconstruct`, backend {jax.default_backend()} ({jax.devices()[0]})"


def parse_args(argv=None):
  p = argparse.ArgumentParser(prog="python -m benchmarks.physics", description=__doc__.split("\n\n")[0])
  p.add_argument("--sizes", type=int, nargs="+", default=[32, 64, 128], help="scan points per side")
  p.add_argument("--bins", type=int, default=512, help="time bins (32 ps)")
  p.add_argument("--methods", nargs="+", default=list(numpy_twins.METHODS),
                 choices=list(numpy_twins.METHODS))
  p.add_argument("--repeats", type=int, default=3, help="timed warm runs per side (median)")
  p.add_argument("--out", type=pathlib.Path, default=None,
                 help="Markdown output (default benchmarks/results/physics.md; with --quick: print only)")
  p.add_argument("--quick", action="store_true",
                 help="smoke test: 32² scan points, 128 bins, no variant study")
  p.add_argument("--time-limit", type=float, default=120.0,
                 help="seconds one step (build, compile, one run) may take before the case is recorded as a timeout")
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--no-jax", action="store_true", help="time the NumPy twins only")
  p.add_argument("--no-variants", action="store_true",
                 help="skip the variant study (public vs refined operators)")
  args = p.parse_args(argv)
  if args.quick:
    args.sizes, args.bins, args.no_variants = [32], 128, True
  if args.out is None and not args.quick:
    args.out = DEFAULT_OUT
  if args.repeats < 1:
    p.error("--repeats must be >= 1")
  return args


def main(argv=None) -> int:
  args = parse_args(argv)
  command = "python -m benchmarks.physics" + (" " + " ".join(sys.argv[1:] if argv is None else argv)).rstrip()
  if args.no_jax:
    with_jax, jax_status = False, "skipped (--no-jax)"
  else:
    with_jax, jax_status = _jax_available()
  print(jax_status, flush=True)

  from tqdm import tqdm

  cases = [(n, m) for n in args.sizes for m in args.methods]
  rows, notes = [], []
  bar = tqdm(cases, desc="cases", unit="case")
  for n, method in bar:
    bar.set_postfix_str(f"{method} {n}² numpy")
    p = run_case(_numpy_worker, method, n, args.bins, args.repeats, args.seed, args.time_limit)
    j = None
    if with_jax:
      bar.set_postfix_str(f"{method} {n}² jax")
      j = run_case(_jax_worker, method, n, args.bins, args.repeats, args.seed, args.time_limit)
    row = {"method": method, "n": n, "bins": args.bins, "numpy": p, "jax": j}
    if j is not None and j.get("status") == "ok" and p.get("status") == "ok":
      row["speedup"] = p["run_s"] / j["run_s"] if j["run_s"] > 0 else None
      row["over_floor"] = j["run_s"] / j["floor_s"] if j.get("floor_s") else None
      row["ncc"] = ncc(p["mip"], j["mip"])
    for side, res in (("NumPy", p), ("JAX", j)):
      if res is None:
        continue
      if res.get("status") != "ok":
        notes.append(f"{method} {n}² {side}: {res['status']}")
        if res.get("traceback"):
          tqdm.write(res["traceback"])
      elif res.get("peak_note"):
        notes.append(f"{method} {n}² {side}: {res['peak_note']}")
    rows.append(row)
    tqdm.write(f"{method:>6} {n:>4}²: numpy {_cell(p, 'run_s', '.4f')} s"
               + (f", jax {_cell(j, 'run_s', '.4f')} s (compile {_cell(j, 'compile_s')} s),"
                  f" speed-up {_fmt(row.get('speedup'), '.2f')}, NCC {_fmt(row.get('ncc'), '.3f')}"
                  if with_jax else ""))
  bar.close()
  study = None
  if with_jax and not args.no_variants:
    print("variant study ...", flush=True)
    study = variant_study()
  text = write_report(args.out, command, args, rows, with_jax, jax_status, notes, study)
  print()
  print(text)
  if args.out is not None:
    print(f"written to {args.out}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
