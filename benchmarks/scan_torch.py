"""Side benchmark: pure-PyTorch parallel selective scans on the shapes of ``benchmarks.scan``.

PyTorch is NOT a dependency of nlosjax; it comes with the optional ``bench`` extra
(install a CPU build of torch first if you do not want its CUDA packages):

    pip install -e ".[bench]"
    python -m benchmarks.scan_torch [--shapes 256x512x32x16 ...] [--repeats 5] [--out FILE]

It writes ``benchmarks/results/scan_torch.md`` whole (``--out``): command, date,
machine, commit and torch version, then one table of forward and
forward+backward medians (ms) per shape, the shapes of ``benchmarks.scan``'s
``scan.md`` so the two files read side by side. Peers:

* ``mambapy``: mambapy's ``pscan`` (the pure-PyTorch Blelloch scan of the
  ``mambapy`` package, its own hand-written backward), fed the same
  ``(exp(dt A), dt x B)`` pairs, then ``y = sum_n h C``; skipped with a note
  when mambapy is not installed (it is in the ``bench`` extra).

our own kernels in the same run and the same way (``nlosjax blockwise`` and
so on: ``selective_scan(method=...)`` jitted, forward and ``value_and_grad``),
so that the ratio to mambapy is measured side by side; the goal is the
associative kernel ("blockwise") at least 5x faster than mambapy forward+backward;
and two parallel formulations written here from their published descriptions,
with PyTorch autograd for the backward:

* ``doubling``: the Hillis-Steele log-depth scan over the materialised pairs
  ``(a, b) = (exp(dt A), dt x B)`` ``[Bt, L, D, N]``: at step ``k = 1, 2, 4, ...``
  ``b[k:] += a[k:] * b[:-k]``, ``a[k:] *= a[:-k]`` (out of place, autograd-friendly);
  then ``y = sum_n h C``. The usual "pure PyTorch pscan" shape of computation.
* ``heinsen``: Heinsen's log-space scan (arXiv:2311.06281): ``log h_t = a*_t +
  logcumsumexp_s<=t(log b_s - a*_s)`` with ``a*_t = cumsum(dt A)`` and a complex log
  for the signed ``b``.

Inputs are those of ``benchmarks.scan.make_inputs`` drawn with NumPy (same
distributions, not the same numbers). Both are checked against a sequential loop
on a small case before timing.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import pathlib
import statistics
import sys
import time

import numpy as np

try:
  import torch
except ImportError:
  raise SystemExit("benchmarks.scan_torch compares against PyTorch, which is not a dependency "
                   "of nlosjax: install the optional extra with  pip install -e \".[bench]\"") from None

try:
  from mambapy.pscan import pscan as mambapy_pscan
except ImportError:
  mambapy_pscan = None

DEFAULT_SHAPES = ("64x512x32x16", "128x256x32x16")   # the shapes of benchmarks.scan
JAX_METHODS = ("blockwise", "sequential", "associative")
GOAL_VS_MAMBAPY = 5.0
DEFAULT_OUT = pathlib.Path(__file__).resolve().parent / "results" / "scan_torch.md"


def mambapy_scan(x, dt, A, B, C):
  """mambapy's ``pscan`` on ``(exp(dt A), dt x B)`` ``[Bt, L, D, N]``, then ``y = sum_n h C``."""
  a = torch.exp(dt.unsqueeze(-1) * A)
  b = (dt * x).unsqueeze(-1) * B.unsqueeze(2)
  return (mambapy_pscan(a, b) * C.unsqueeze(2)).sum(-1)


def doubling_scan(x, dt, A, B, C):
  """x, dt [Bt, L, D]; A [D, N]; B, C [Bt, L, N] -> y [Bt, L, D] (no D skip)."""
  a = torch.exp(dt.unsqueeze(-1) * A)
  b = (dt * x).unsqueeze(-1) * B.unsqueeze(2)
  L = x.shape[1]
  k = 1
  while k < L:
    b = torch.cat([b[:, :k], a[:, k:] * b[:, :-k] + b[:, k:]], dim=1)
    a = torch.cat([a[:, :k], a[:, k:] * a[:, :-k]], dim=1)
    k *= 2
  return (b * C.unsqueeze(2)).sum(-1)


def heinsen_scan(x, dt, A, B, C):
  """Log-space scan: h = exp(a* + logcumsumexp(log b - a*)), complex log for signed b."""
  a_star = torch.cumsum(dt.unsqueeze(-1) * A, dim=1)                      # [Bt, L, D, N]
  b = (dt * x).unsqueeze(-1) * B.unsqueeze(2)
  log_b = torch.log(b.to(torch.complex64))
  h = torch.exp(a_star + torch.logcumsumexp(log_b - a_star, dim=1)).real
  return (h * C.unsqueeze(2)).sum(-1)


def sequential_scan(x, dt, A, B, C):
  h = torch.zeros(x.shape[0], x.shape[2], A.shape[1], dtype=x.dtype)
  ys = []
  for t in range(x.shape[1]):
    h = torch.exp(dt[:, t, :, None] * A) * h + (dt[:, t] * x[:, t])[..., None] * B[:, t, None, :]
    ys.append((h * C[:, t, None, :]).sum(-1))
  return torch.stack(ys, 1)


def make_inputs(shape, seed=0):
  Bt, L, D, N = shape
  rng = np.random.default_rng(seed)
  x = rng.normal(size=(Bt, L, D))
  dt = np.log1p(np.exp(rng.normal(size=(Bt, L, D)) - 3.0))
  A = -np.arange(1.0, N + 1) * np.exp(0.1 * rng.normal(size=(D, N)))
  B, C = rng.normal(size=(Bt, L, N)), rng.normal(size=(Bt, L, N))
  w = rng.normal(size=(Bt, L, D))
  return [torch.tensor(v, dtype=torch.float32) for v in (x, dt, A, B, C, w)]


def timed(fn, repeats):
  fn()
  ts = []
  for _ in range(repeats):
    t0 = time.perf_counter()
    fn()
    ts.append(time.perf_counter() - t0)
  return statistics.median(ts)


def main(argv=None):
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("--shapes", nargs="+", default=list(DEFAULT_SHAPES))
  p.add_argument("--repeats", type=int, default=5)
  p.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)))
  p.add_argument("--out", type=pathlib.Path, default=DEFAULT_OUT)
  args = p.parse_args(argv)
  from experiments import provenance as _machine
  command = "python -m benchmarks.scan_torch " + " ".join(sys.argv[1:] if argv is None else argv)
  facts = _machine.provenance(command.strip())
  t_start = time.perf_counter()
  torch.set_num_threads(args.threads)
  methods = [doubling_scan, heinsen_scan] + ([mambapy_scan] if mambapy_pscan is not None else [])
  small = make_inputs((2, 37, 3, 4))
  ref = sequential_scan(*small[:5])
  for fn in methods:
    err = float((fn(*small[:5]) - ref).abs().max() / ref.abs().max())
    assert err < 1e-4, (fn.__name__, err)
  rows = []
  ctx = multiprocessing.get_context("spawn")
  names = [fn.__name__.removesuffix("_scan") for fn in methods] + [f"nlosjax {m}" for m in JAX_METHODS]
  both_s = {}
  for s in args.shapes:
    for name in names:
      # Each case in a child process, so one killed for memory (heinsen keeps
      # complex64 [Bt, L, D, N] tensors for autograd) is reported, not fatal.
      queue = ctx.Queue()
      child = ctx.Process(target=_measure, args=(s, name, args.repeats, args.threads, queue))
      child.start()
      child.join()
      try:
        result = queue.get(timeout=5)
      except Exception:                # queue.Empty: the child died before reporting
        result = None
      if result is None:
        fwd, both = f"did not finish (child exit code {child.exitcode}; most likely out of memory)", ""
      elif "error" in result:
        fwd, both = f"failed: {result['error']}", ""
      else:
        fwd, both = f"{result['fwd'] * 1e3:.1f}", f"{result['both'] * 1e3:.1f}"
        both_s[(s, name)] = result["both"]
      rows.append(f"| {s} | {name} | {fwd} | {both} |")
      print(rows[-1], flush=True)
  ratios = []
  for s in args.shapes:
    if (s, "mambapy") not in both_s:
      continue
    for m in JAX_METHODS:
      if (s, f"nlosjax {m}") in both_s:
        r = both_s[(s, "mambapy")] / both_s[(s, f"nlosjax {m}")]
        goal = (f" ({'met' if r >= GOAL_VS_MAMBAPY else 'NOT met'}, goal >= {GOAL_VS_MAMBAPY}x)"
                if m == "blockwise" else "")
        ratios.append(f"- {s}: mambapy fwd+bwd / nlosjax {m} fwd+bwd = {r:.2f}x{goal}")
  mamba_note = ("mambapy " + _dist_version("mambapy") if mambapy_pscan is not None else
                "mambapy not installed (`pip install -e \".[bench]\"`): its row is missing")
  lines = ["# Pure-PyTorch parallel selective scans (peers, not dependencies)", "", *facts,
           f"- torch {torch.__version__} on the CPU, {args.threads} threads; {mamba_note}",
           f"- Wall time: {(time.perf_counter() - t_start) / 60:.1f} min", "",
           "Same scan as `benchmarks.scan` (`h_t = exp(dt_t A) h_{t-1} + dt_t x_t B_t`, "
           "`y_t = C_t h_t`, no D skip) on inputs with the same distributions (not the same "
           "numbers). Each method is first checked against a sequential loop on a "
           "(2, 37, 3, 4) case (max error < 1e-4 of the peak). Shape = (batch, length, "
           "channels, state). Medians of "
           f"{args.repeats} calls after one warm-up, ms; read beside `scan.md`'s rows of the "
           "same shape, measured by its own command.", "",
           "- `doubling`: Hillis-Steele log-depth scan over the materialised "
           "`(exp(dt A), dt x B)` pairs, autograd backward.",
           "- `heinsen`: Heinsen's log-space scan (arXiv:2311.06281), complex log for the "
           "signed inputs, autograd backward.",
           "- `mambapy`: the `mambapy` package's `pscan` (Blelloch up/down sweeps in place, "
           "its own backward).", "",
           "- `nlosjax <method>`: `nlosjax.ssm.selective_scan(method=...)`, jitted, the same "
           "loss `sum(y * w)` and gradients for x, dt, A, B, C (JAX's own threads; "
           "compile excluded).", "",
           "| shape | method | fwd ms | fwd+bwd ms |", "|---|---|---|---|", *rows, "",
           "Speed-up over mambapy, forward+backward (same run):", "", *ratios, ""]
  args.out.parent.mkdir(parents=True, exist_ok=True)
  args.out.write_text("\n".join(lines))
  print(f"wrote {args.out}")


def _measure(shape_text: str, name: str, repeats: int, threads: int, queue) -> None:
  """Child process: time one method at one shape; puts ``{"fwd", "both"}`` (s) or ``{"error"}``."""
  if name.startswith("nlosjax "):
    queue.put(_measure_jax(shape_text, name.removeprefix("nlosjax "), repeats))
    return
  torch.set_num_threads(threads)
  fn = globals()[f"{name}_scan"]
  x, dt, A, B, C, w = make_inputs(tuple(int(v) for v in shape_text.split("x")))
  try:
    with torch.no_grad():
      fwd = timed(lambda: fn(x, dt, A, B, C), repeats)
    leaves = [v.clone().requires_grad_(True) for v in (x, dt, A, B, C)]

    def fwd_bwd():
      for v in leaves:
        v.grad = None
      (fn(*leaves) * w).sum().backward()
    queue.put({"fwd": fwd, "both": timed(fwd_bwd, repeats)})
  except RuntimeError as e:
    queue.put({"error": str(e).splitlines()[0][:80]})


def _measure_jax(shape_text: str, method: str, repeats: int) -> dict:
  """Time ``selective_scan(method=method)`` forward and forward+backward, as ``benchmarks.scan`` does."""
  import jax

  from benchmarks.scan import build_variants
  from benchmarks.scan import make_inputs as jax_inputs
  args, w = jax_inputs(tuple(int(v) for v in shape_text.split("x")))
  variants = build_variants([method], None, w)
  fwd, both = (jax.jit(variants[(method, ps)]) for ps in ("fwd", "fwd+bwd"))
  return {"fwd": timed(lambda: jax.block_until_ready(fwd(*args)), repeats),
          "both": timed(lambda: jax.block_until_ready(both(*args)), repeats)}


def _dist_version(name: str) -> str:
  import importlib.metadata
  try:
    return importlib.metadata.version(name)
  except importlib.metadata.PackageNotFoundError:
    return "unknown"


if __name__ == "__main__":
  main()
