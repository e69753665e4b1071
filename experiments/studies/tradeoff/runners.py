"""Running a configuration: compile time, XLA memory and outputs (:func:`evaluate`), and the
warm time per call of every executable, timed round-robin (:func:`interleaved_times`).
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

MIB = 1024.0 ** 2


def _padded(inputs: np.ndarray, batch: int) -> np.ndarray:
  """``inputs [N, ...]`` padded to a multiple of ``batch`` by repeating the last example."""
  if len(inputs) == 0:
    raise ValueError("inputs is empty")
  pad = (-len(inputs)) % batch
  return np.concatenate([inputs, np.repeat(inputs[-1:], pad, axis=0)]) if pad else inputs


def evaluate(fn: Callable, inputs: np.ndarray, *, batch: int, cache: dict, key,
             params=None) -> dict:
  """Compile ``fn`` once per ``key`` and run it over ``inputs`` in batches.

  Args:
    fn: ``fn(x) -> dict`` (or ``fn(params, x)`` when ``params`` is given)
      with ``"intensity"`` and ``"depth"`` ``[B, H, W]``; jitted here.
    inputs: ``[N, ...]`` examples; the last batch is padded by repeating the
      last example and its extra outputs dropped.
    batch: examples per call.
    cache: ``key -> {"executable", "args", "compile_s", "mem_mib"}``. When
      ``key`` is there its executable is reused (the same computation on
      other data, e.g. another exposure); otherwise ``fn`` is compiled
      (``.lower(first batch).compile()``, timed) and stored with its
      first-batch arguments, for :func:`interleaved_times`.
    key: hashable name of the computation.
    params: an optional first argument (a pytree, e.g. network parameters).
  Returns:
    ``{"outputs": {"intensity", "depth": [N, H, W]}, "compile_s", "mem_mib"
    (XLA temp + argument + output bytes), "key"}``.
  """
  import jax
  if batch < 1:
    raise ValueError(f"batch must be >= 1, got {batch}")
  n = len(inputs)
  x = _padded(inputs, batch)
  wrap = (lambda xb: (params, xb)) if params is not None else (lambda xb: (xb,))
  if key not in cache:
    args0 = wrap(jax.device_put(x[:batch]))
    t = time.perf_counter()
    compiled = jax.jit(fn).lower(*args0).compile()
    compile_s = time.perf_counter() - t
    mem = compiled.memory_analysis()
    mem_mib = (float("nan") if mem is None else
               (mem.temp_size_in_bytes + mem.argument_size_in_bytes + mem.output_size_in_bytes) / MIB)
    cache[key] = {"executable": compiled, "args": args0, "compile_s": compile_s,
                  "mem_mib": mem_mib}
  entry = cache[key]
  outs = {"intensity": [], "depth": []}
  for i in range(0, len(x), batch):
    o = entry["executable"](*wrap(jax.device_put(x[i:i + batch])))
    for k in outs:
      outs[k].append(np.asarray(o[k]))
  return {"outputs": {k: np.concatenate(v)[:n] for k, v in outs.items()},
          "compile_s": entry["compile_s"], "mem_mib": entry["mem_mib"], "key": key}


def interleaved_times(fns: dict, inputs: dict, *, rounds: int) -> dict:
  """Seconds per call of already-compiled ``fns[k](*inputs[k])``, timed round-robin.

  One untimed warm-up round, then ``rounds`` rounds of one call of every
  function each (ended by ``block_until_ready``), so a change in the
  machine's load hits every function alike and their ratios stay
  meaningful on a shared machine.

  Returns:
    ``{k: [seconds of each round]}``; take the median.
  """
  import jax
  if rounds < 1:
    raise ValueError(f"rounds must be >= 1, got {rounds}")
  for k, f in fns.items():
    jax.block_until_ready(f(*inputs[k]))
  times = {k: [] for k in fns}
  for _ in range(rounds):
    for k, f in fns.items():
      t = time.perf_counter()
      jax.block_until_ready(f(*inputs[k]))
      times[k].append(time.perf_counter() - t)
  return times
