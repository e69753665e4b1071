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

To run one path on any platform, trace the function inside :func:`cpu_paths` (every switch
takes its CPU-tuned branch) or :func:`accelerator_paths` (every switch takes the other),
e.g. to time both programs on the same GPU::

    with platforms.cpu_paths():
      compiled = jax.jit(step).lower(*args).compile()

The choice is made while the function is traced; the override is part of JAX's tracing and
compilation cache key, so a function traced before (or inside another override) is traced
again, nested ``jit`` functions included. It holds for the thread that entered it.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

import jax

#: The platform name ``jax.lax.platform_dependent`` gives the CPU-tuned branch.
CPU = "cpu"
#: The value :func:`forced` gives inside :func:`accelerator_paths`.
ACCELERATOR = "accelerator"

# None (choose by the lowering platform), CPU or ACCELERATOR. A JAX user context: thread-local
# when entered, and part of the jit cache key, so a change of value retraces.
_FORCED = jax.make_user_context(default_value=None)


def forced() -> str | None:
  """The path forced in this thread (:data:`CPU` or :data:`ACCELERATOR`), or None where the platform chooses."""
  return _FORCED.value


@contextlib.contextmanager
def _force(path: str | None) -> Iterator[None]:
  with _FORCED(path):
    yield


def cpu_paths() -> contextlib.AbstractContextManager[None]:
  """Context manager: functions traced inside it take every switch's CPU-tuned branch, on any platform.

  While it is active in a thread, :func:`by_platform` calls ``cpu(*args)`` directly: a
  program traced there holds the CPU-tuned constructs even when it is lowered for CUDA.
  Nests with :func:`accelerator_paths` (the innermost wins); on exit the previous choice
  comes back. Programs traced outside it are unchanged.
  """
  return _force(CPU)


def accelerator_paths() -> contextlib.AbstractContextManager[None]:
  """Context manager: functions traced inside it take every switch's accelerator branch, on any platform.

  The counterpart of :func:`cpu_paths`: :func:`by_platform` calls ``other(*args)``
  directly, so a program run on a CPU holds the constructs a GPU program holds.
  """
  return _force(ACCELERATOR)


def by_platform(*args, cpu: Callable, other: Callable):
  """``cpu(*args)`` in a program lowered for the CPU, ``other(*args)`` for any other platform.

  ``cpu`` and ``other`` take the same ``args`` (arrays or pytrees of arrays) and return
  the same shapes and dtypes. Differentiable, and usable under ``vmap`` and in a
  ``custom_vjp`` rule. Inside :func:`cpu_paths` it is ``cpu(*args)``, inside
  :func:`accelerator_paths` ``other(*args)``, whatever the platform.
  """
  path = _FORCED.value
  if path == CPU:
    return cpu(*args)
  if path == ACCELERATOR:
    return other(*args)
  return jax.lax.platform_dependent(*args, cpu=cpu, default=other)
