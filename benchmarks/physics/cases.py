"""One side of one case (JAX or the NumPy/SciPy twin) timed in a fresh child process that reports each step."""

from __future__ import annotations

import multiprocessing
import resource
import statistics
import time
import traceback
import tracemalloc

import numpy as np

from benchmarks.physics.scene import fft_floor, make_setup, synthetic_transient
from experiments import numpy_twins


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
        "status": "out of memory" if oom else f"error: {type(e).__name__}: {first_line(e)}",
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
    conn.send(("result", {"status": f"error: {type(e).__name__}: {first_line(e)}",
                          "traceback": traceback.format_exc()}))


def first_line(e: BaseException, limit: int = 120) -> str:
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
