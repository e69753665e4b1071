"""Seconds per scan of ``experiments.reconstruct`` beside the NumPy/SciPy twins, and warm calls."""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np

from experiments.studies.real_undersampling.protocol import OPTIONS, REPO

_TWIN_SCRIPT = r"""
import json, sys, time
t0 = time.perf_counter()
from experiments import numpy_twins as twins
t1 = time.perf_counter()
x, setup = twins.load_published(sys.argv[1])
t2 = time.perf_counter()
ops = twins.build(setup, sys.argv[2], **json.loads(sys.argv[3]))
t3 = time.perf_counter()
vol = twins.run(x, sys.argv[2], ops)
t4 = time.perf_counter()
vol = twins.run(x, sys.argv[2], ops)
t5 = time.perf_counter()
print(json.dumps({"load_s": t2 - t1, "build_s": t3 - t2, "run_s": t4 - t3, "warm_run_s": t5 - t4,
                  "import_s": t1 - t0}))
"""


def _python_env() -> dict:
  env = dict(os.environ)
  env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
  return env


def time_cli(path, methods=("lct", "fk", "phasor"), repeats: int = 3, log=print) -> dict:
  """Wall times of ``experiments.reconstruct`` (cold and with a warm XLA cache) and of the NumPy twins.

  Each configuration runs ``repeats`` times in fresh processes, alternating
  methods; the median is kept. Returns ``method -> {...}``.
  """
  env = _python_env()
  out = {}
  with tempfile.TemporaryDirectory() as tmp:
    for method in methods:
      opts = OPTIONS[method]
      flags = []
      if "snr" in opts:
        flags += ["--snr", str(opts["snr"])]
      if "falloff" in opts:
        flags += ["--falloff", opts["falloff"]]
      rows = {"cold": [], "cached": [], "twin": []}
      cache = pathlib.Path(tmp) / f"xla_{method}"
      for r in range(repeats):
        for kind in ("cold", "cached", "twin"):
          t0 = time.perf_counter()
          if kind == "twin":
            res = subprocess.run([sys.executable, "-c", _TWIN_SCRIPT, str(path), method, json.dumps(opts)],
                                 env=env, cwd=REPO, capture_output=True, text=True, check=True)
            rec = json.loads(res.stdout.strip().splitlines()[-1])
          else:
            e = dict(env, NLOSJAX_CACHE_DIR=str(cache))
            cmd = [sys.executable, "-m", "experiments.reconstruct", str(path), "--method", method,
                   "--out", str(pathlib.Path(tmp) / f"{method}_{kind}"), "--quiet", *flags]
            if kind == "cold":
              cmd.append("--no-cache")
            elif r == 0:      # fill the cache once before the timed cached runs
              subprocess.run(cmd, env=e, cwd=REPO, capture_output=True, check=True)
              t0 = time.perf_counter()
            subprocess.run(cmd, env=e, cwd=REPO, capture_output=True, check=True)
            rec = json.loads((pathlib.Path(tmp) / f"{method}_{kind}" / "timings.json").read_text())
          rec["process_s"] = time.perf_counter() - t0
          rows[kind].append(rec)
      med = lambda rs, k: float(np.median([x[k] for x in rs]))
      out[method] = {
          "cli_cold": {k: med(rows["cold"], k) for k in ("load_s", "reconstruct_s", "process_s")},
          "cli_cached": {k: med(rows["cached"], k) for k in ("load_s", "reconstruct_s", "process_s")},
          "twin": {k: med(rows["twin"], k) for k in ("load_s", "build_s", "run_s", "warm_run_s",
                                                     "import_s", "process_s")},
          "repeats": repeats}
      log(f"timing {method}: {json.dumps(out[method])}")
  return out


def time_warm(path, methods=("lct", "fk", "phasor"), repeats: int = 5) -> dict:
  """In-process warm run times (compiled, operators built): JAX ``reconstruct`` vs the twin's run."""
  import jax

  from experiments import numpy_twins as twins
  from nlosjax import physics
  from nlosjax.data import io
  x, setup = io.load_measurement(path)
  out = {}
  for m in methods:
    fn = lambda a, m=m: physics.reconstruct(a, setup, m, **OPTIONS[m])   # jitted inside
    jax.block_until_ready(fn(x))
    ops = twins.build(setup, m, **OPTIONS[m])
    twins.run(x, m, ops)
    tj, tn = [], []
    for _ in range(repeats):
      t0 = time.perf_counter()
      jax.block_until_ready(fn(x))
      tj.append(time.perf_counter() - t0)
      t0 = time.perf_counter()
      twins.run(x, m, ops)
      tn.append(time.perf_counter() - t0)
    out[m] = {"jax_run_s": float(np.median(tj)), "twin_run_s": float(np.median(tn))}
  return out
