"""Side benchmark: pure-PyTorch parallel selective scans on the shapes of ``benchmarks.scan``.

PyTorch is NOT a dependency of nlosjax; it comes with the optional ``bench`` extra
(install a CPU build of torch first if you do not want its CUDA packages):

    pip install -e ".[bench]"
    python -m benchmarks.scan_torch [--shapes 256x512x32x16 ...] [--repeats 5]

It prints one Markdown table (forward and forward+backward medians, ms) to paste
next to ``benchmarks/results/scan.md``. Two parallel formulations, both written
here from their published descriptions, with PyTorch autograd for the backward:

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
import os
import platform
import statistics
import time

import numpy as np

try:
  import torch
except ImportError:
  raise SystemExit("benchmarks.scan_torch compares against PyTorch, which is not a dependency "
                   "of nlosjax: install the optional extra with  pip install -e \".[bench]\"") from None

DEFAULT_SHAPES = ("256x512x32x16", "64x128x16x16", "512x256x32x16")


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


def main():
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  p.add_argument("--shapes", nargs="+", default=list(DEFAULT_SHAPES))
  p.add_argument("--repeats", type=int, default=5)
  p.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)))
  args = p.parse_args()
  torch.set_num_threads(args.threads)
  small = make_inputs((2, 37, 3, 4))
  ref = sequential_scan(*small[:5])
  for fn in (doubling_scan, heinsen_scan):
    err = float((fn(*small[:5]) - ref).abs().max() / ref.abs().max())
    assert err < 1e-4, (fn.__name__, err)
  print(f"torch {torch.__version__}, {args.threads} threads, Python {platform.python_version()}")
  print("| shape | method | fwd ms | fwd+bwd ms |")
  print("|---|---|---|---|")
  for s in args.shapes:
    shape = tuple(int(v) for v in s.split("x"))
    x, dt, A, B, C, w = make_inputs(shape)
    for fn in (doubling_scan, heinsen_scan):
      with torch.no_grad():
        fwd = timed(lambda: fn(x, dt, A, B, C), args.repeats)
      leaves = [v.clone().requires_grad_(True) for v in (x, dt, A, B, C)]

      def fwd_bwd():
        for v in leaves:
          v.grad = None
        (fn(*leaves) * w).sum().backward()
      both = timed(fwd_bwd, args.repeats)
      print(f"| {s} | torch {fn.__name__} | {fwd * 1e3:.2f} | {both * 1e3:.2f} |", flush=True)


if __name__ == "__main__":
  main()
