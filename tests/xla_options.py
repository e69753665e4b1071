"""XLA switches the test modules share (not a test module)."""

import contextlib
import json
import os

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


def user_environment(environ=None) -> dict:
  """``environ`` (default ``os.environ``) as a user has it: without the suite's speed settings.

  ``conftest.py`` turns XLA's optimisations off and switches XLA:CPU's emitters for the
  suite's tiny programs, recording the variables' values before (``NLOSJAX_TEST_USER_XLA``).
  A command a user would run as written (the README's and ``docs/``' code blocks) runs with
  those values back: on jaxlib 0.10.2 the two settings together crashed the shipped network's
  jitted forward now and then (a segmentation fault) where neither alone did.
  """
  env = dict(os.environ if environ is None else environ)
  recorded = env.pop("NLOSJAX_TEST_USER_XLA", None)
  if recorded is None:
    return env
  for name, value in json.loads(recorded).items():
    if value is None:
      env.pop(name, None)
    else:
      env[name] = value
  return env
