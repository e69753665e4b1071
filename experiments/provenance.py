"""Provenance of a results file: the command, date, machine (CPU model, cores, memory, load) and commit.

One place for the ``/proc`` reading that every results file's header needs:
the benchmarks (``benchmarks/*.py``) and the experiments that write results
(``experiments.real_undersampling``) import it from here, so arrows run
downward (``nlosjax`` <- ``experiments`` <- ``benchmarks``).
"""

from __future__ import annotations

import os
import platform


def _proc_field(path: str, key: str) -> str | None:
  """The value after ``key:`` on the first matching line of ``path``, or None."""
  try:
    with open(path) as f:
      for line in f:
        name, sep, value = line.partition(":")
        if sep and name.strip() == key:      # cpuinfo pads names with tabs
          return value.strip()
  except OSError:
    pass
  return None


def cpu_model() -> str:
  """The CPU's model name (``/proc/cpuinfo``), else what ``platform`` knows."""
  return _proc_field("/proc/cpuinfo", "model name") or platform.processor() or platform.machine()


def usable_cores() -> int:
  """Cores this process may run on (its affinity mask), else the logical count."""
  try:
    return len(os.sched_getaffinity(0))
  except AttributeError:
    return os.cpu_count() or 1


def memory_gib() -> float | None:
  """Physical memory in GiB (``/proc/meminfo``), or None where unknown."""
  value = _proc_field("/proc/meminfo", "MemTotal")
  if value is None:
    return None
  return int(value.split()[0]) / 1024 ** 2


def memory_text() -> str:
  """``"23.5 GiB"`` or ``"unknown"``."""
  gib = memory_gib()
  return "unknown" if gib is None else f"{gib:.1f} GiB"


def load_average(sep: str = " ") -> str:
  """1, 5 and 15 minute load averages, or ``"n/a"``."""
  try:
    return sep.join(f"{v:.2f}" for v in os.getloadavg())
  except OSError:
    return "n/a"


def git_commit(repo=None) -> str:
  """The checked-out commit (short hash), with ``+changes`` when tracked code differs from it.

  Changes under ``benchmarks/results/`` (what benchmarks write) do not count.

  ``"unknown"`` outside a git checkout. A results file names this so a reader
  can check out the code that wrote it.
  """
  import pathlib
  import subprocess
  where = pathlib.Path(repo) if repo else pathlib.Path(__file__).resolve().parents[1]
  try:
    head = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=where, check=True,
                          capture_output=True, text=True).stdout.strip()
    # Results files written by this or another benchmark are not code: they do not count.
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ".",
                            ":(exclude)benchmarks/results"], cwd=where,
                           check=True, capture_output=True, text=True).stdout.strip()
  except (OSError, subprocess.CalledProcessError):
    return "unknown"
  return head + (" +changes (uncommitted edits to tracked files)" if dirty else "")


def provenance(command: str) -> list[str]:
  """Markdown lines every results file starts with: command, date, machine, commit."""
  import datetime

  import jax
  return [f"Produced by `{command}`.", "",
          f"- Date: {datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds')}",
          f"- Machine: {cpu_model()}; {usable_cores()} usable cores; memory {memory_text()}; "
          f"JAX backend {jax.default_backend()} ({jax.devices()[0].device_kind}); "
          f"Python {platform.python_version()}, jax {jax.__version__}",
          f"- Commit: {git_commit()}",
          f"- Load average (1, 5, 15 min) when written: {load_average(', ')}"]
