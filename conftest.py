"""Suite-wide pytest setup: the test extra must be installed; two xdist workers by default.

The README's test command is ``pip install -e ".[test]" && python -m pytest -q``.
Run without the test extra, the suite used to fail with argparse's
"unrecognized arguments: -n" (the worker count sat in ``addopts``) or an
ImportError deep in one module. Here instead:

* every requirement of the ``test`` extra, read from the installed package's
  metadata (so this list cannot drift from ``pyproject.toml``), is checked
  before collection, and a missing one stops the run with the install command;
* the suite is compile-bound, so it runs on 2 xdist workers, one module per
  worker (``-n 2 --dist loadfile``), unless the command line says otherwise
  (``-n 0`` runs in one process, ``-n 4`` on four, ``-p no:xdist`` disables it);
* XLA's optimisations are off by default (``JAX_DISABLE_MOST_OPTIMIZATIONS=1``, unless
  the environment sets it): tiny programs compile several times faster without them;
  the modules whose programs run long turn them back on;
* XLA:CPU's older elemental emitters instead of its fusion emitters
  (``--xla_cpu_use_fusion_emitters=false`` added to ``XLA_FLAGS``, where this jaxlib
  knows the flag and the environment does not set it): the tiny model's gradient
  compiles in about 0.6x the time (the same operations, emitted another way);
* the suite compiles the same small programs many times (every tiny training run
  compiles the same train step), so one persistent XLA compilation cache, in a
  temporary folder made for this run and removed after it, is shared by every
  worker and every subprocess (environment variables set before the workers
  start): the second compile of a program is a disk read. JAX writes cache
  entries without renaming them into place, so a size limit is set: that makes
  JAX lock the folder (with ``filelock``, in the test extra) around every read
  and write, and no process reads an entry another is still writing. Without
  ``filelock`` the cache stays off. A run never reads executables from an
  earlier run or the user's own cache (``~/.cache/nlosjax``); folders left by
  killed runs are removed by the next run. ``NLOSJAX_TEST_CACHE=0`` turns it
  off; a ``JAX_COMPILATION_CACHE_DIR`` already set is used as it is (and kept).
"""

from __future__ import annotations

import importlib.metadata
import os
import re
import shutil
import tempfile

import pytest

DEFAULT_WORKERS = 2
INSTALL = 'pip install -e ".[test]"'


def missing_test_requirements() -> list[str]:
  """Names of the ``test`` extra's distributions that are not installed (``[]`` if all are).

  Raises:
    pytest.UsageError: nlosjax itself is not installed in this interpreter.
  """
  try:
    requires = importlib.metadata.requires("nlosjax") or []
  except importlib.metadata.PackageNotFoundError:
    raise pytest.UsageError(f"nlosjax is not installed in this interpreter; from the "
                            f"repository root run: {INSTALL}") from None
  missing = []
  for requirement in requires:
    name, _, marker = requirement.partition(";")
    if not re.search(r"""extra\s*==\s*["']test["']""", marker):
      continue
    dist = re.match(r"\s*([A-Za-z0-9._-]+)", name).group(1)
    try:
      importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
      missing.append(dist)
  return missing


@pytest.hookimpl(wrapper=True)
def pytest_cmdline_main(config: pytest.Config):
  """Default to ``-n 2 --dist loadfile`` where pytest-xdist is active and ``-n`` was not given."""
  if (config.pluginmanager.hasplugin("xdist") and not hasattr(config, "workerinput")
      and config.getoption("numprocesses", None) is None):
    config.option.numprocesses = DEFAULT_WORKERS
    if config.getoption("dist", "no") == "no":
      config.option.dist = "loadfile"
  return (yield)


# Measured on 2 cores: tests/test_train_resume.py 97 s without the cache, 55 s with a cold one.
CACHE_PREFIX = "nlosjax-test-xla-"
CACHE_ENV = {"JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
             "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES": "0",
             # Any limit switches on JAX's file lock; 64 GiB never evicts here.
             "JAX_COMPILATION_CACHE_MAX_SIZE": str(64 * 2 ** 30)}


def _pid_alive(pid: int) -> bool:
  try:
    os.kill(pid, 0)
  except ProcessLookupError:
    return False
  except PermissionError:
    return True
  return True


def remove_stale_caches(parent: str | None = None) -> list[str]:
  """Delete cache folders of earlier runs whose pytest process is gone; returns their paths."""
  parent = parent or tempfile.gettempdir()
  removed = []
  for entry in os.scandir(parent):
    if not (entry.name.startswith(CACHE_PREFIX) and entry.is_dir()):
      continue
    try:
      pid = int(open(os.path.join(entry.path, "pid")).read())
    except (OSError, ValueError):
      pid = None                       # no pid file: made by an older conftest, or half made
    if pid is None or not _pid_alive(pid):
      shutil.rmtree(entry.path, ignore_errors=True)
      removed.append(entry.path)
  return removed


def shared_compilation_cache(environ) -> str | None:
  """Point JAX (and ``experiments.reconstruct``'s cache) at a fresh folder via ``environ``.

  Returns the folder this call made (the caller removes it at the end), or ``None``
  when the cache is switched off (``NLOSJAX_TEST_CACHE=0``), the environment
  already names one, or ``filelock`` is missing (JAX's lock needs it).
  ``NLOSJAX_TEST_CACHE_DIR`` names the folder made here, so a test can tell it from
  one the user gave.
  """
  if environ.get("NLOSJAX_TEST_CACHE", "1") == "0" or environ.get("JAX_COMPILATION_CACHE_DIR"):
    return None
  try:
    import filelock  # noqa: F401  (JAX imports it to lock the cache)
  except ImportError:
    return None
  path = tempfile.mkdtemp(prefix=CACHE_PREFIX)
  with open(os.path.join(path, "pid"), "w") as f:
    f.write(str(os.getpid()))
  environ["JAX_COMPILATION_CACHE_DIR"] = environ["NLOSJAX_TEST_CACHE_DIR"] = path
  environ["NLOSJAX_CACHE_DIR"] = path        # experiments.reconstruct.enable_compilation_cache
  for key, value in CACHE_ENV.items():
    environ.setdefault(key, value)
  return path


def pytest_configure(config: pytest.Config) -> None:
  if hasattr(config, "workerinput"):
    return                         # the controller has checked already and set the cache
  missing = missing_test_requirements()
  if missing:
    raise pytest.UsageError(f"the test extra is not fully installed (missing: "
                            f"{', '.join(missing)}); from the repository root run: {INSTALL}")
  # Before JAX is imported here and before the xdist workers start, so both read it.
  if os.environ.get("NLOSJAX_TEST_CACHE", "1") != "0":
    remove_stale_caches()
  config._nlosjax_cache = shared_compilation_cache(os.environ)
  # The suite compiles hundreds of tiny programs and runs few of them long: without XLA's
  # optimisations they compile several times faster (the temporal probe's test: 36 s -> 10 s).
  # Modules whose programs run long (measured scans, samplers, rendering) switch them back on
  # with tests.xla_options.xla_optimizations(True). Set before the workers and subprocesses start.
  os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")
  os.environ["XLA_FLAGS"] = suite_xla_flags(os.environ.get("XLA_FLAGS", ""))


#: XLA flags the suite adds (name -> value), each only where the environment does not set it.
#: Measured on 2 EPYC cores, tiny Ours' gradient: 5.1 s -> 3.2 s to compile, its train step 7.1 -> 5.0 s.
SUITE_XLA_FLAGS = {"--xla_cpu_use_fusion_emitters": "false"}


def _xla_flag_known(flag: str) -> bool:
  """Whether this jaxlib starts with ``flag`` in ``XLA_FLAGS`` (XLA aborts on unknown flags)."""
  import subprocess
  import sys
  env = {**os.environ, "XLA_FLAGS": flag, "JAX_PLATFORMS": "cpu"}
  res = subprocess.run([sys.executable, "-c", "import jax; jax.devices()"], env=env,
                       capture_output=True, timeout=120)
  return res.returncode == 0


def suite_xla_flags(current: str, known=_xla_flag_known) -> str:
  """``current`` with each of :data:`SUITE_XLA_FLAGS` appended, unless named there or unknown."""
  flags = current.split()
  for name, value in SUITE_XLA_FLAGS.items():
    if any(f.split("=")[0] == name for f in flags):
      continue
    flag = f"{name}={value}"
    if known(flag):
      flags.append(flag)
  return " ".join(flags)


def pytest_unconfigure(config: pytest.Config) -> None:
  path = getattr(config, "_nlosjax_cache", None)
  if path:
    shutil.rmtree(path, ignore_errors=True)
