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
  compiles the same train step), so it shares the clone's persistent XLA compilation
  cache (``.cache/xla``, ignored by git; ``NLOSJAX_CACHE_DIR`` names another folder)
  with the main job, set up by ``experiments.xla_cache`` for every worker and
  subprocess (environment variables set before the workers start): a program compiled
  by another test, worker or earlier run is a disk read. XLA keys entries by program,
  versions and flags, so an edited program compiles afresh. JAX writes entries without
  renaming them into place, so a size limit is set: that makes JAX lock the folder
  (with ``filelock``) around every read and write, and no process reads an entry
  another is still writing. Without ``filelock`` the cache stays off.
  Only programs that take at least :data:`SUITE_MIN_COMPILE_S` to compile are written
  (``JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS``, which the environment may set; the main
  job writes every program): the unit tier compiles thousands of tiny programs, each op of
  an eager call among them, and writing each under the folder's lock cost more than it
  saved. Measured on 2 cores (``tests/test_conv_impl.py`` and ``tests/test_losses.py``,
  ``-n 0``, beside a training run): from an empty cache 55.9 s writing every program, 36.3 s
  writing those over 1 s, 36.3 s with no cache; run again on the cache so written, 22.9 s
  and 28.5 s.
  ``NLOSJAX_TEST_CACHE=0`` (or ``NLOSJAX_CACHE=0``, which the main job reads too) turns it
  off. The terminal summary ends with the cache's hit rate over the suite's processes:
  each xdist worker, and each subprocess that enables the cache itself, writes its
  counts into a folder made for this run (removed after it, or by the next run where
  this one was killed).
"""

from __future__ import annotations

import glob
import importlib.metadata
import json
import os
import re
import shutil
import tempfile

import pytest

DEFAULT_WORKERS = 2
#: The suite's persistent cache keeps programs that took at least this many seconds to compile.
SUITE_MIN_COMPILE_S = "1"
INSTALL = 'pip install -e ".[test]"'
#: Test tiers (``--tier``): ``default`` (the README's command) runs every test not marked
#: ``@pytest.mark.full``; ``full`` runs only those (the end-to-end claims: shipped weights
#: reproduced, the main job, distributed training, the studies and their reports, training runs
#: killed and resumed, the CLIs run end to end, the docs' examples, the whole network under
#: extreme inputs and under checks); ``all`` runs both.
#: ``bash .ci/run`` runs the default tier, then the full one.
TIERS = ("default", "full", "all")


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


def pytest_addoption(parser) -> None:
  parser.addoption("--tier", choices=TIERS, default=os.environ.get("NLOSJAX_TEST_TIER", "default"),
                   help="default: the unit tier (tests not marked full); full: the end-to-end tier "
                        "(marked full); all: both (env NLOSJAX_TEST_TIER)")


def pytest_collection_modifyitems(config: pytest.Config, items: list) -> None:
  """Keep the tests of ``--tier`` (:data:`TIERS`); the others are reported as deselected."""
  tier = config.getoption("tier")
  if tier == "all":
    return
  keep, drop = [], []
  for item in items:
    (keep if (item.get_closest_marker("full") is not None) == (tier == "full") else drop).append(item)
  if drop:
    config.hook.pytest_deselected(items=drop)
    items[:] = keep


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
#: Per-run folders (the workers' cache counts) start with this; ``nlosjax-test-xla-`` is the
#: per-run cache folder of earlier versions of this file, removed the same way.
RUN_PREFIX = "nlosjax-test-run-"
STALE_PREFIXES = (RUN_PREFIX, "nlosjax-test-xla-")


def _pid_alive(pid: int) -> bool:
  try:
    os.kill(pid, 0)
  except ProcessLookupError:
    return False
  except PermissionError:
    return True
  return True


def remove_stale_runs(parent: str | None = None) -> list[str]:
  """Delete per-run folders of earlier runs whose pytest process is gone; returns their paths."""
  parent = parent or tempfile.gettempdir()
  removed = []
  for entry in os.scandir(parent):
    if not (entry.name.startswith(STALE_PREFIXES) and entry.is_dir()):
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
  """Point JAX, the workers and every subprocess at the clone's persistent cache via ``environ``.

  Returns the folder (``experiments.xla_cache.configure``: ``.cache/xla`` in the clone, or
  ``NLOSJAX_CACHE_DIR``, or a ``JAX_COMPILATION_CACHE_DIR`` already set), or ``None`` when
  the cache is off (only programs compiling for :data:`SUITE_MIN_COMPILE_S` or longer are
  written, unless ``environ`` says otherwise): ``NLOSJAX_TEST_CACHE=0`` (which sets ``NLOSJAX_CACHE=0``, so a command
  a test runs keeps it off too), ``NLOSJAX_CACHE=0``, or ``filelock`` missing.
  """
  from experiments import xla_cache
  if environ.get("NLOSJAX_TEST_CACHE", "1") == "0":
    environ[xla_cache.SWITCH_ENV] = "0"
    return None
  environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", SUITE_MIN_COMPILE_S)
  return xla_cache.configure(environ, tidy=True)


def counts_folder(environ) -> str:
  """A folder for this run's cache counts, named in ``environ`` (``NLOSJAX_CACHE_COUNTS``)."""
  from experiments import xla_cache
  path = tempfile.mkdtemp(prefix=RUN_PREFIX)
  with open(os.path.join(path, "pid"), "w") as f:
    f.write(str(os.getpid()))
  environ[xla_cache.COUNTS_ENV] = path
  return path


def pytest_configure(config: pytest.Config) -> None:
  config.addinivalue_line("markers", "full: an end-to-end claim, run in the full tier (--tier full; "
                                     "bash .ci/run runs it after the default tier)")
  if hasattr(config, "workerinput"):
    from experiments import xla_cache
    if os.environ.get(xla_cache.COUNTS_ENV):        # the controller set the cache up
      xla_cache.count()
      _listen_to_compiles()
    return                         # the controller has checked already and set the cache
  missing = missing_test_requirements()
  if missing:
    raise pytest.UsageError(f"the test extra is not fully installed (missing: "
                            f"{', '.join(missing)}); from the repository root run: {INSTALL}")
  # Before JAX is imported here and before the xdist workers start, so both read it.
  remove_stale_runs()
  config._nlosjax_cache = shared_compilation_cache(os.environ)
  config._nlosjax_counts = counts_folder(os.environ) if config._nlosjax_cache else None
  # The suite compiles hundreds of tiny programs and runs few of them long: without XLA's
  # optimisations they compile several times faster (the temporal probe's test: 36 s -> 10 s).
  # Modules whose programs run long (measured scans, samplers, rendering) switch them back on
  # with tests.xla_options.xla_optimizations(True). Set before the workers and subprocesses start.
  from tests.xla_options import record_user_environment
  record_user_environment(os.environ)        # tests.xla_options.user_environment restores these
  os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")
  os.environ["XLA_FLAGS"] = suite_xla_flags(os.environ.get("XLA_FLAGS", ""))
  if config._nlosjax_cache and not getattr(config.option, "numprocesses", None):
    from experiments import xla_cache
    xla_cache.count()              # -n 0 or without xdist: the tests compile in this process
    _listen_to_compiles()


#: XLA compiles per test in this process (test id -> [compiles, seconds compiling]), for the
#: summary's "most compiles" lines: a test that runs its model or loss operation by operation
#: compiles each operation alone (hundreds of programs), which :func:`jax.jit` turns into one.
_COMPILES: dict[str, list] = {}
_CURRENT: list = [None]
COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
MOST_COMPILES = 8


def _on_compile(event: str, duration: float, **kwargs) -> None:
  if event == COMPILE_EVENT and _CURRENT[0] is not None:
    row = _COMPILES.setdefault(_CURRENT[0], [0, 0.0])
    row[0] += 1
    row[1] += duration


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
  _CURRENT[0] = item.nodeid
  try:
    yield
  finally:
    _CURRENT[0] = None


def _listen_to_compiles() -> None:
  import jax.monitoring
  jax.monitoring.register_event_duration_secs_listener(_on_compile)


def pytest_sessionfinish(session: pytest.Session) -> None:
  """A worker writes its cache and compile counts for the controller (before xdist reports it finished)."""
  from experiments import xla_cache
  folder = os.environ.get(xla_cache.COUNTS_ENV)
  if hasattr(session.config, "workerinput") and folder:
    xla_cache.write_counts(folder)
    # Not .json: xla_cache.read_counts reads every .json file there as one process's cache counts.
    with open(os.path.join(folder, f"{os.getpid()}.compiles"), "w") as f:
      json.dump(_COMPILES, f)


def most_compiles(config: pytest.Config, n: int = MOST_COMPILES) -> list[str]:
  """Lines naming the ``n`` tests that compiled most, over every test process of this run."""
  rows = dict(_COMPILES)
  folder = getattr(config, "_nlosjax_counts", None)
  for path in glob.glob(os.path.join(folder, "*.compiles")) if folder else ():
    with open(path) as f:
      rows.update(json.load(f))
  if not rows:
    return []
  total, seconds = sum(r[0] for r in rows.values()), sum(r[1] for r in rows.values())
  top = sorted(rows.items(), key=lambda kv: -kv[1][0])[:n]
  return ([f"XLA programs built (compiled or read from the cache): {total} in {len(rows)} tests, {seconds:.0f} s;"
           " most:"]
          + [f"  {c:5d} programs {s:6.1f} s  {name}" for name, (c, s) in top])


def cache_summary(config: pytest.Config) -> str | None:
  """The hit-rate line over this run's processes (``None`` where ``pytest_configure`` did not run)."""
  from experiments import xla_cache
  if not hasattr(config, "_nlosjax_cache"):
    return None
  path, folder = config._nlosjax_cache, config._nlosjax_counts
  if not path:
    why = ("NLOSJAX_TEST_CACHE=0" if os.environ.get("NLOSJAX_TEST_CACHE") == "0"
           else "NLOSJAX_CACHE=0" if os.environ.get(xla_cache.SWITCH_ENV) == "0"
           else "the filelock package, which JAX locks the folder with, is not installed")
    return f"XLA compilation cache: off ({why})"
  totals, processes = xla_cache.read_counts(folder)
  own = xla_cache.counts()
  if own["requests"]:
    processes += 1
    totals = {k: totals[k] + own[k] for k in totals}
  where = f"over {processes} test process{'es' * (processes != 1)}" if processes else ""
  return xla_cache.summary(totals, path, where=where)


def pytest_terminal_summary(terminalreporter, exitstatus, config: pytest.Config) -> None:
  if hasattr(config, "workerinput"):
    return
  line = cache_summary(config)
  if line:
    terminalreporter.write_line(line)
  for line in most_compiles(config):
    terminalreporter.write_line(line)
  from tests.faults import summary  # the fault campaign's tally (tests/test_faults.py), when it ran
  reports = [r for group in terminalreporter.stats.values() for r in group if hasattr(r, "user_properties")]
  for line in summary(reports):
    terminalreporter.write_line(line)


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
  folder = getattr(config, "_nlosjax_counts", None)
  if folder:
    shutil.rmtree(folder, ignore_errors=True)
