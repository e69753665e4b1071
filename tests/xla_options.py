"""XLA switches the test modules share (not a test module)."""

import contextlib

import jax


@contextlib.contextmanager
def xla_optimizations(enabled: bool):
  """Turn XLA's optimisations on or off inside the block, restoring the previous setting after.

  Tiny shapes compile faster without them; loops such as the Poisson sampler's
  rejection loop run faster with them.
  """
  prev = jax.config.read("jax_disable_most_optimizations")
  jax.config.update("jax_disable_most_optimizations", not enabled)
  try:
    yield
  finally:
    jax.config.update("jax_disable_most_optimizations", prev)
