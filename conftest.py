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
  (``-n 0`` runs in one process, ``-n 4`` on four, ``-p no:xdist`` disables it).
"""

from __future__ import annotations

import importlib.metadata
import re

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


def pytest_configure(config: pytest.Config) -> None:
  if hasattr(config, "workerinput"):
    return                         # the controller has checked already
  missing = missing_test_requirements()
  if missing:
    raise pytest.UsageError(f"the test extra is not fully installed (missing: "
                            f"{', '.join(missing)}); from the repository root run: {INSTALL}")
