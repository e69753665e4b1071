"""Provenance of a results file: the command, date, machine (CPU model, cores, memory, load) and commit.

One place for the ``/proc`` reading that every results file's header needs:
the benchmarks (``benchmarks/*.py``) and the experiments that write results
(``experiments.studies.real_undersampling``) import it from here, so arrows run
downward (``nlosjax`` <- ``experiments`` <- ``benchmarks``).

Each header also carries a ``- Code:`` line: a digest of the project's modules that
the command may run (:func:`code_line`), with their list, so ``python -m benchmarks.index``
can recompute the digest on today's tree and say whether the file is current or stale,
instead of a person writing "still holds" banners by hand.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import os
import pathlib
import platform
import re
import sys
from collections.abc import Callable, Collection, Iterable


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


def _lscpu() -> dict[str, str]:
  """``lscpu``'s fields (name -> value), or ``{}`` where it is missing or fails."""
  import subprocess
  try:
    out = subprocess.run(["lscpu"], capture_output=True, text=True, timeout=10,
                         env={**os.environ, "LC_ALL": "C"}).stdout
  except (OSError, subprocess.SubprocessError):
    return {}
  return {k.strip(): v.strip() for k, sep, v in (line.partition(":") for line in out.splitlines()) if sep}


def cpu_facts() -> dict:
  """The CPU's ``model``, ``mhz`` (a float, or None) and ``cache`` (text as reported, or None).

  Machines of one model name differ (1.5-2x in this project's timings): the clock and the
  cache tell them apart. ``/proc/cpuinfo``'s first processor (``cpu MHz``: its clock when
  read; ``cache size``: the per-core cache it reports, L2 on AMD, L3 on Intel), else
  ``lscpu`` (``CPU MHz`` or ``CPU max MHz``; the largest of L3, L2 it lists).
  """
  mhz = _proc_field("/proc/cpuinfo", "cpu MHz")
  cache = _proc_field("/proc/cpuinfo", "cache size")
  if mhz is None or cache is None:
    fields = _lscpu()
    mhz = mhz or fields.get("CPU MHz") or fields.get("CPU max MHz")
    level = next((k for k in ("L3 cache", "L2 cache") if fields.get(k)), None)
    cache = cache or (f"{level.split()[0]} {fields[level]}" if level else None)
  try:
    mhz = round(float(mhz), 1) if mhz is not None else None
  except ValueError:
    mhz = None
  return {"model": cpu_model(), "mhz": mhz, "cache": cache}


def cpu_text(facts: dict | None = None, model: bool = True) -> str:
  """``"AMD EPYC, 2596 MHz, cache 1024 KB"``: :func:`cpu_facts` in one line (unknowns left out).

  ``model=False``: the clock and cache alone (``""`` where neither is known).
  """
  facts = cpu_facts() if facts is None else facts
  parts = [facts["model"]] if model else []
  if facts.get("mhz"):
    parts.append(f"{facts['mhz']:.0f} MHz")
  if facts.get("cache"):
    parts.append(f"cache {facts['cache']}")
  return ", ".join(parts)


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

  Changes under ``benchmarks/results/`` and ``experiments/studies/*/results/`` (what benchmarks and
  studies write) and ``experiments/studies/*/state/`` (the resumable state a long run exports as it
  trains) do not count.

  ``"unknown"`` outside a git checkout. A results file names this so a reader
  can check out the code that wrote it.
  """
  import pathlib
  import subprocess
  where = pathlib.Path(repo) if repo else pathlib.Path(__file__).resolve().parents[1]
  try:
    head = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=where, check=True,
                          capture_output=True, text=True).stdout.strip()
    # Results files and run states written by benchmarks, studies and runs are not code.
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ".",
                            ":(exclude)benchmarks/results", ":(exclude,glob)experiments/studies/*/results/**",
                            ":(exclude,glob)experiments/studies/*/state/**"],
                           cwd=where, check=True, capture_output=True, text=True).stdout.strip()
  except (OSError, subprocess.CalledProcessError):
    return "unknown"
  return head + (" +changes (uncommitted edits to tracked files)" if dirty else "")


def machine_text() -> str:
  """One line of hardware for a results header: CPU, clock and cache, cores, memory, JAX backend.

  ``"AMD EPYC; 2596 MHz, cache 1024 KB; 2 usable cores (2 logical); memory 23.5 GiB; JAX
  backend cpu (cpu)"`` (the backend part says so where JAX is not installed).
  """
  import os
  try:
    import jax
    dev = jax.devices()[0]
    backend = f"JAX backend {jax.default_backend()} ({getattr(dev, 'device_kind', dev)})"
  except ImportError:
    backend = "JAX not installed"
  return (f"{cpu_model()}; {_clock_and_cache()}{usable_cores()} usable cores ({os.cpu_count()} logical); "
          f"memory {memory_text()}; {backend}")


def versions_text(*packages: str) -> str:
  """``"Python 3.11.7, jax 0.10.2"`` and each of ``packages``' installed version (or "absent")."""
  import importlib.metadata
  names = ("jax",) + tuple(p for p in packages if p != "jax")
  found = []
  for name in names:
    try:
      found.append(f"{name} {importlib.metadata.version(name)}")
    except importlib.metadata.PackageNotFoundError:
      found.append(f"{name} absent")
  return ", ".join([f"Python {platform.python_version()}"] + found)


def provenance(command: str, modules: Iterable[str] | None = None) -> list[str]:
  """Markdown lines every results file starts with: command, date, machine, commit, code digest.

  ``modules``: the project modules the command may run (default: :func:`code_modules` of
  :func:`command_roots`, this process's); a writer whose code runs in a subprocess it chooses
  by its arguments names them (``benchmarks.equivalence --probe``).
  """
  import datetime

  return [f"Produced by `{command}`.", "",
          f"- Date: {datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds')}",
          f"- Machine: {machine_text()}; {versions_text()}",
          f"- Commit: {git_commit()}",
          code_line(modules),
          f"- Load average (1, 5, 15 min) when written: {load_average(', ')}"]


def _clock_and_cache() -> str:
  """``"2596 MHz, cache 1024 KB; "`` for a results header (empty where neither is known)."""
  text = cpu_text(model=False)
  return f"{text}; " if text else ""


def machine_record() -> dict:
  """Where and from which code this process runs, JSON-ready.

  ``date`` (UTC, now), ``commit`` (:func:`git_commit`), ``cpu``, ``cpu_mhz`` and
  ``cpu_cache`` (:func:`cpu_facts`), ``cores``, ``memory``, ``backend``, ``device``,
  ``python``, ``jax`` and ``load_average``.
  A training run's record (:func:`run_record`) and a mechanism-study run's
  ``machine`` are this.
  """
  import datetime

  import jax
  facts = cpu_facts()
  return {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
          "commit": git_commit(), "cpu": facts["model"], "cpu_mhz": facts["mhz"], "cpu_cache": facts["cache"],
          "cores": usable_cores(), "memory": memory_text(),
          "backend": jax.default_backend(), "device": jax.devices()[0].device_kind,
          "python": platform.python_version(), "jax": jax.__version__,
          "load_average": load_average(", ")}


def run_record(command: str) -> dict:
  """:func:`machine_record` with the ``command`` that starts a training process.

  ``python -m experiments.train`` appends one per invocation to
  ``<workdir>/invocations.jsonl``; ``experiments.export_weights`` reads it.
  """
  return {"command": command, **machine_record()}


# --- What a results file's numbers depend on: the project's code, by content -----------------

PACKAGES = ("nlosjax", "experiments", "benchmarks")
ROOT = pathlib.Path(__file__).resolve().parents[1]
# Commands that run other project entry points in a subprocess (their imports are not ours).
SUBPROCESS_ROOTS = {"benchmarks.main_job": ("experiments.train",)}
# Modules every writer imports that write a header, not a number: a change to them leaves
# every results file's numbers as they were, so they are not part of any digest.
NOT_CODE = frozenset({"experiments/provenance.py"})
CODE_LINE = re.compile(r"^- Code: `([0-9a-f]{12,64})`.*<!-- modules: ([^>]*?) -->\s*$", re.MULTILINE)


def _module_file(name: str, files: Collection[str]) -> str | None:
  """Repository-relative path of project module ``name`` (``"a/b.py"`` or ``"a/b/__init__.py"``), or None."""
  parts = name.split(".")
  if parts[0] not in PACKAGES:
    return None
  base = "/".join(parts)
  for candidate in (base + ".py", base + "/__init__.py"):
    if candidate in files:
      return candidate
  return None


def _imported_names(path: str, source: str, files: Collection[str]) -> set[str]:
  """Every module name ``path``'s code may import, at any depth (function-level imports too).

  ``from a import b`` yields both ``a`` and ``a.b`` (``b`` may be a submodule); relative
  imports are resolved against ``path``'s package. A module that calls
  ``importlib.import_module`` with a name made at run time (the config registry picks a
  preset by name) may import any module of its own package, so all of them count. Names that are not project modules are
  filtered out later.
  """
  is_init = path.endswith("/__init__.py")
  module = path[:-len("/__init__.py")].replace("/", ".") if is_init else path[:-3].replace("/", ".")
  package = module if is_init else module.rsplit(".", 1)[0]
  names = set()
  for node in ast.walk(ast.parse(source, filename=path)):
    if isinstance(node, ast.Import):
      for alias in node.names:
        parts = alias.name.split(".")
        names.update(".".join(parts[:i]) for i in range(1, len(parts) + 1))
    elif isinstance(node, ast.ImportFrom):
      if node.level:
        base = package.split(".")
        base = base[:len(base) - node.level + 1]
        mod = ".".join(base + ([node.module] if node.module else []))
      else:
        mod = node.module or ""
      parts = mod.split(".")
      names.update(".".join(parts[:i]) for i in range(1, len(parts) + 1))
      names.update(f"{mod}.{alias.name}" for alias in node.names)
    elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
          and node.func.attr == "import_module" and node.args):
      arg = node.args[0]
      if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
        names.add(arg.value)
      else:                                        # a name made at run time: any module beside it
        folder = package.replace(".", "/") + "/"
        names.update(f[:-3].replace("/", ".") for f in files
                     if f.startswith(folder) and "/" not in f[len(folder):] and f.endswith(".py"))
  return names


def project_files(root: pathlib.Path = ROOT) -> set[str]:
  """The ``.py`` files of the project's packages in the working tree, repository-relative."""
  return {p.relative_to(root).as_posix() for pkg in PACKAGES for p in (root / pkg).rglob("*.py")}


def code_modules(roots: Iterable[str], files: Collection[str] | None = None,
                 read: Callable[[str], str] | None = None) -> list[str]:
  """The project files that ``roots`` (module names) import, transitively, sorted.

  A static closure over the import statements (including those inside functions, so a lazy
  import counts), with each module's enclosing packages' ``__init__.py``. It is a superset
  of what one run loads, so a results file is called stale whenever code it may have run
  changed. ``files``/``read`` default to this working tree; pass others to read a commit.
  :data:`NOT_CODE` is left out.
  """
  files = project_files() if files is None else files
  read = read or (lambda p: (ROOT / p).read_text())
  todo = list(roots)
  seen: set[str] = set()
  while todo:
    name = todo.pop()
    parts = name.split(".")
    for i in range(1, len(parts) + 1):            # importing a.b.c runs a and a.b first
      path = _module_file(".".join(parts[:i]), files)
      if path is None or path in seen:
        continue
      seen.add(path)
      todo.extend(_imported_names(path, read(path), files))
  return sorted(seen - NOT_CODE)


@functools.lru_cache(maxsize=4096)
def _behaviour(source: str, path: str = "<module>") -> str:
  """``source``'s syntax tree without docstrings, as text: comments, layout and docs do not count.

  The text is Python 3.11's ``ast.dump`` on every Python from 3.11 on (3.12 added an empty
  ``type_params`` to each function and class and empty pieces to nested f-string formats, 3.13
  leaves empty lists out), so a results file
  written on a machine with another Python (the GPU image's 3.12) has a comparable digest.
  """
  tree = ast.parse(source, filename=path)
  for node in ast.walk(tree):
    body = getattr(node, "body", None)
    if (isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and body
        and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)
        and isinstance(body[0].value.value, str)):
      node.body = body[1:] or [ast.Pass()]
    if getattr(node, "type_params", None) == []:  # a field Python 3.12 added: absent in 3.11's text
      del node.type_params
    if isinstance(node, ast.JoinedStr):             # 3.12's f-string parser adds empty pieces
      node.values = [v for v in node.values if not (isinstance(v, ast.Constant) and v.value == "")]
  if sys.version_info >= (3, 13):                 # 3.13 leaves empty lists out unless asked
    return ast.dump(tree, annotate_fields=False, show_empty=True)
  return ast.dump(tree, annotate_fields=False)


def code_digest(paths: Iterable[str], read: Callable[[str], str] | None = None) -> str:
  """12 hex digits of the SHA-256 of the modules' paths and code (in sorted path order).

  The code is each module's syntax tree without docstrings (:func:`_behaviour`), so an edit
  to a comment, a docstring or the layout leaves the digest as it was; any other edit,
  behaviour-keeping or not, changes it.
  """
  read = read or (lambda p: (ROOT / p).read_text())
  h = hashlib.sha256()
  for p in sorted(paths):
    h.update(p.encode() + b"\0" + _behaviour(read(p), p).encode() + b"\0")
  return h.hexdigest()[:12]


def command_roots(extra: Iterable[str] = ()) -> list[str]:
  """This process's project modules: ``__main__``'s, every loaded one, ``extra`` and their subprocesses'.

  ``python -m pkg`` runs ``pkg/__main__.py`` as ``__main__``: both ``pkg`` and ``pkg.__main__``
  are roots (the command line's own code counts; before, only the package's ``__init__`` did).
  """
  roots = set(extra)
  main = getattr(sys.modules.get("__main__"), "__spec__", None)
  if main is not None and main.name:
    roots.add(main.name)
    if main.name.endswith(".__main__"):
      roots.add(main.name[:-len(".__main__")])
  roots.update(name for name in list(sys.modules) if name.split(".")[0] in PACKAGES)
  for r in list(roots):
    roots.update(SUBPROCESS_ROOTS.get(r, ()))
  return sorted(roots)


def code_line(paths: Iterable[str] | None = None, digest: str | None = None, note: str = "") -> str:
  """The results header line ``- Code: `digest` ...`` that ``python -m benchmarks.index`` rechecks.

  ``paths`` default to :func:`code_modules` of :func:`command_roots` (this process);
  the list rides along in an HTML comment, so the rendered file shows one short line.
  """
  paths = code_modules(command_roots()) if paths is None else sorted(paths)
  digest = digest or code_digest(paths)
  return (f"- Code: `{digest}` = SHA-256 of the {len(paths)} project modules this command may run "
          f"(their static import closure; code only, not comments or docstrings){note}; "
          f"`python -m benchmarks.index` recomputes it to say whether this file is current "
          f"<!-- modules: {' '.join(paths)} -->")


def recompute_at_commit(text: str) -> str | None:
  """``text`` (a results file) with its code digest recomputed here from its recorded commit, or None.

  A digest is a function of a commit's code, but a file written on another machine was
  digested by that machine's Python; before :func:`_behaviour` gave every Python from 3.11 on
  the same text, the GPU image's 3.12 gave another digest for the same code. For a file
  written from a clean tree (its ``- Commit:`` line without ``+changes``) at a commit git has,
  the digest is recomputed from that commit's files; the line then says so. None where the
  file has no such commit or code line, or the recomputed digest is the recorded one.

  Raises:
    ValueError: git lacks the recorded commit, or one of the recorded modules at it.
  """
  import subprocess
  code = CODE_LINE.search(text)
  commit = re.search(r"^- Commit: ([0-9a-f]{7,40})\s*$", text, re.MULTILINE)
  if not code or not commit:
    return None

  def read(path: str) -> str:
    got = subprocess.run(["git", "show", f"{commit.group(1)}:{path}"], cwd=ROOT,
                         capture_output=True, text=True)
    if got.returncode:
      raise ValueError(f"git has no {path} at commit {commit.group(1)}, which the file records: "
                       f"{got.stderr.strip()}")
    return got.stdout

  modules = code.group(2).split()
  digest = code_digest(modules, read)
  if digest == code.group(1):
    return None
  note = (f", recomputed by `python -m experiments.provenance --recompute` from commit {commit.group(1)}"
          f" (where it was written, its Python gave `{code.group(1)}` for the same code)")
  return text[:code.start()] + code_line(modules, digest, note) + text[code.end():]


def main(argv=None) -> int:
  """``python -m experiments.provenance --recompute FILE ...``: see :func:`recompute_at_commit`."""
  import argparse
  p = argparse.ArgumentParser(description="Recompute results files' code digests from their recorded commits.")
  p.add_argument("--recompute", nargs="+", type=pathlib.Path, metavar="FILE", required=True)
  for path in p.parse_args(argv).recompute:
    new = recompute_at_commit(path.read_text())
    if new is not None:
      path.write_text(new)
    print(f"{path}: {'recomputed' if new is not None else 'unchanged'}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
