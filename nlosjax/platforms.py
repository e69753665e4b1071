"""The one switch between the CPU-tuned paths and the accelerator paths: :func:`by_platform`.

Some of nlosjax's constructs were chosen because they are fastest on XLA:CPU and are
pathological on XLA:GPU (a weight gradient computed as a forward convolution with a
window the size of the image, a gather whose backward is a colliding scatter, FFTs one
feature channel at a time at lengths with a prime factor 11). Each such place computes
the same numbers two ways and picks by the platform the program is **lowered for**
(``jax.lax.platform_dependent``), not by the process's ``jax.default_backend()``: a
program lowered or exported for CUDA from a CPU host
(``jit(f).trace(...).lower(lowering_platforms=("cuda",))``) holds the accelerator path,
and a program lowered for one platform holds that platform's branch alone (no
``conditional`` is left in it). The CPU branch is the code as it was, so programs run on
a CPU are unchanged.

Both branches of every switch are traced (each must accept the same arguments and give
the same shapes and dtypes); each is a plain function that the tests call directly and
compare with the other on a CPU.
"""

from __future__ import annotations

from collections.abc import Callable

import jax

#: The platform name ``jax.lax.platform_dependent`` gives the CPU-tuned branch.
CPU = "cpu"


def by_platform(*args, cpu: Callable, other: Callable):
  """``cpu(*args)`` in a program lowered for the CPU, ``other(*args)`` for any other platform.

  ``cpu`` and ``other`` take the same ``args`` (arrays or pytrees of arrays) and return
  the same shapes and dtypes. Differentiable, and usable under ``vmap`` and in a
  ``custom_vjp`` rule.
  """
  return jax.lax.platform_dependent(*args, cpu=cpu, default=other)
