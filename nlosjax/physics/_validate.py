"""Input checks shared by the physics functions (run before any compilation)."""

from __future__ import annotations

import contextlib
import contextvars
import functools

import jax
import jax.numpy as jnp
import numpy as np

from nlosjax.physics.setup import Setup


def is_concrete(x) -> bool:
  """True when ``x`` holds values (not a tracer inside ``jit``/``vmap``)."""
  return not isinstance(x, jax.core.Tracer)


def working_dtype(x) -> jnp.dtype:
  """float64 when the input is float64 and x64 is on, else float32."""
  if jnp.dtype(getattr(x, "dtype", np.float32)) == jnp.float64 and jax.config.jax_enable_x64:
    return jnp.dtype(jnp.float64)
  return jnp.dtype(jnp.float32)


#: True while :func:`nlosjax.physics.checks.checked` traces a function: traced counts
#: then get ``checkify`` checks (elsewhere, under a plain ``jit``, they cost nothing).
_TRACED_CHECKS = contextvars.ContextVar("nlosjax_traced_checks", default=False)


@contextlib.contextmanager
def traced_checks():
  """Within this block, :func:`check_counts` of a traced array adds ``checkify`` checks."""
  token = _TRACED_CHECKS.set(True)
  try:
    yield
  finally:
    _TRACED_CHECKS.reset(token)


def check_counts(x, name: str) -> None:
  """Raise ValueError if concrete ``x`` holds NaN, inf or negative values.

  A traced ``x`` is checked only inside :func:`nlosjax.physics.checks.checked`
  (as ``checkify`` checks, raised when the compiled function runs).
  """
  if not is_concrete(x):
    if _TRACED_CHECKS.get():
      from jax.experimental import checkify
      checkify.check(jnp.all(jnp.isfinite(x)), f"{name} holds NaN or infinite values")
      checkify.check(jnp.all(x >= 0), f"{name} holds negative values; photon counts must be >= 0")
    return
  arr = np.asarray(x)      # host-side: safe while another function is being traced
  if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)
          or arr.dtype == jnp.bfloat16):
    raise ValueError(f"{name} must be a real array of counts, got dtype {arr.dtype}")
  bad_nan = not bool(np.all(np.isfinite(arr)))
  bad_neg = bool(np.any(arr < 0))
  if bad_nan:
    raise ValueError(f"{name} holds NaN or infinite values")
  if bad_neg:
    raise ValueError(f"{name} holds negative values; photon counts must be >= 0")


def prepare_transient(transient, setup: Setup, name: str = "transient"):
  """Validate ``[..., T, H, W]`` against ``setup``; return ``(x [B, T, H, W], batch_shape)``."""
  if not isinstance(setup, Setup):
    raise ValueError(f"setup must be a nlosjax.physics.Setup, got {type(setup).__name__}")
  setup.check_transient(transient, name)
  check_counts(transient, name)
  x = jnp.asarray(transient)
  x = x.astype(working_dtype(x))
  batch_shape = x.shape[:-3]
  return x.reshape((-1,) + x.shape[-3:]), batch_shape


def unbatch(y, batch_shape):
  """``[B, ...]`` -> ``[*batch_shape, ...]``."""
  return y.reshape(tuple(batch_shape) + y.shape[1:])


def check_positive(value, name: str) -> float:
  """A finite float > 0, or ValueError naming ``name``."""
  try:
    v = float(value)
  except (TypeError, ValueError):
    raise ValueError(f"{name} must be a number, got {value!r}") from None
  if not np.isfinite(v) or v <= 0:
    raise ValueError(f"{name} must be finite and > 0, got {value!r}")
  return v


def cached_operators(maxsize: int):
  """``functools.lru_cache`` for operator builders, always evaluated eagerly.

  A builder first reached inside a user's ``jax.jit`` would otherwise cache
  tracers of that trace, and every later call would fail with
  ``UnexpectedTracerError``; ``jax.ensure_compile_time_eval`` makes the cached
  operators concrete arrays whatever the calling context.
  """
  def wrap(fn):
    cached = functools.lru_cache(maxsize=maxsize)(fn)

    @functools.wraps(fn)
    def build(*args, **kwargs):
      with jax.ensure_compile_time_eval():
        return cached(*args, **kwargs)
    build.cache_clear = cached.cache_clear
    build.cache_info = cached.cache_info
    return build
  return wrap
