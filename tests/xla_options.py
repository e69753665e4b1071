"""XLA switches the test modules share (not a test module).

Imports no JAX at module level: ``conftest.py`` calls :func:`record_user_environment`
before JAX is first imported.
"""

import contextlib
import json
import os

#: Where the suite records the environment's own XLA settings before it changes them (JSON).
USER_ENV = "NLOSJAX_TEST_USER_XLA"
#: The variables the suite changes for speed (conftest.py).
SUITE_VARIABLES = ("JAX_DISABLE_MOST_OPTIMIZATIONS", "XLA_FLAGS")


@contextlib.contextmanager
def xla_optimizations(enabled: bool):
  """Turn XLA's optimisations on or off inside the block, restoring the previous setting after.

  Tiny shapes compile faster without them; loops such as the Poisson sampler's
  rejection loop run faster with them.
  """
  import jax

  prev = jax.config.read("jax_disable_most_optimizations")
  jax.config.update("jax_disable_most_optimizations", not enabled)
  try:
    yield
  finally:
    jax.config.update("jax_disable_most_optimizations", prev)


def record_user_environment(environ) -> None:
  """Record in ``environ`` the values of :data:`SUITE_VARIABLES` before the suite changes them."""
  environ[USER_ENV] = json.dumps({name: environ.get(name) for name in SUITE_VARIABLES})


def user_environment(environ=None) -> dict:
  """``environ`` (default ``os.environ``) as a user has it: without the suite's speed settings.

  ``conftest.py`` turns XLA's optimisations off and switches XLA:CPU's emitters for the
  suite's tiny programs, recording the variables' values before (:func:`record_user_environment`).
  A command a user would run as written (the README's and ``docs/``' code blocks) runs with
  those values back: on jaxlib 0.10.2 the two settings together crashed the shipped network's
  jitted forward now and then (a segmentation fault) where neither alone did.
  """
  env = dict(os.environ if environ is None else environ)
  recorded = env.pop(USER_ENV, None)
  if recorded is None:
    return env
  for name, value in json.loads(recorded).items():
    if value is None:
      env.pop(name, None)
    else:
      env[name] = value
  return env
