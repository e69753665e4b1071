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

Modules: :mod:`~benchmarks.physics.scene` (the capture and the FFT floors),
:mod:`~benchmarks.physics.cases` (one side of a case in a child process),
:mod:`~benchmarks.physics.variants` (the operator-variant study),
:mod:`~benchmarks.physics.report` (the Markdown report), and :mod:`~benchmarks.physics.cli` (the command line).
"""

from benchmarks.physics.cases import TWIN_OPTIONS, run_case
from benchmarks.physics.report import GOAL_FLOOR, GOAL_SIZES, GOAL_SPEEDUP, goal_summary, ncc, write_report
from benchmarks.physics.scene import BIN_WIDTH, WALL_SIZE, fft_floor, make_setup, synthetic_transient
from benchmarks.physics.variants import VARIANT_ROWS, variant_study

__all__ = ["BIN_WIDTH", "GOAL_FLOOR", "GOAL_SIZES", "GOAL_SPEEDUP", "TWIN_OPTIONS", "VARIANT_ROWS", "WALL_SIZE",
           "fft_floor", "goal_summary", "make_setup", "ncc", "run_case", "synthetic_transient", "variant_study",
           "write_report"]
