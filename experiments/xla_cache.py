"""One persistent XLA compilation cache for the project's commands, and its hit rate.

Compiling dominates the first minutes of the main job and most of the test suite on
a CPU, and a second run compiles again what the first compiled. JAX can keep the
compiled programs (XLA executables) on disk and read them back instead
(``jax_compilation_cache_dir``). The commands of a clone share one folder, so
a second run, or a test that builds the program another test built, reads it:

* every command (``python -m experiments.train``, the main job; ``reconstruct``,
  ``evaluate``, ``make_dataset``, ``demo``) calls :func:`enable` before it compiles,
  unless given ``--no-cache`` (:func:`add_argument`, :func:`enable_unless`: for timing a
  cold start); the test suite's ``conftest.py`` calls :func:`configure` before JAX is
  imported and its xdist workers start;
* the folder: ``NLOSJAX_CACHE_DIR`` if set, else ``JAX_COMPILATION_CACHE_DIR`` if set,
  else ``.cache/xla`` in the clone (git ignores it), or ``~/.cache/nlosjax/xla``
  where this module is not in a source tree;
* ``NLOSJAX_CACHE=0`` switches it off (``NLOSJAX_TEST_CACHE=0``: for the test suite only).

XLA keys an entry by the program, the JAX and jaxlib versions, the backend, the
compile options and ``XLA_FLAGS``, so an edited program, another version or other
flags never read a stale entry: they compile and write their own. (An XLA:CPU entry
that the loader finds was compiled for other CPU features is refused and compiled
again, so a folder copied between machines is safe, if useless.)

Several processes may share the folder (the suite's workers, concurrent runs), and
JAX writes an entry in place, without renaming: a size limit is set because that is
what makes JAX lock the folder (with ``filelock``) around every read and write, so
no process reads an entry another is still writing. Without ``filelock`` the cache
stays off. The limit (:data:`MAX_SIZE`, ``JAX_COMPILATION_CACHE_MAX_SIZE`` overrides)
also bounds the folder: the least recently read entries go first.

With a limit JAX also lists the whole folder at every write (about 50 us per entry on
2 busy cores), so a folder that only grows, as edited programs leave their old entries
behind, makes every compile dearer. The main job and the test suite therefore
:func:`prune` it when they start: entries no run has read for :data:`PRUNE_AFTER_DAYS`
days go, and beyond :data:`MAX_ENTRIES` the least recently read.

:func:`summary` is the line each command prints at its end: how many of this
process's compiles were read from the cache (JAX's monitoring events
``/jax/compilation_cache/compile_requests_use_cache`` and ``.../cache_hits``) and
the compile time they saved. Processes that run under one command (the suite's
workers) write their counts with :func:`write_counts` for the command to add up
(:func:`read_counts`).

Only what this module sets up is JAX's own: nothing here changes what a program
computes, only whether it is compiled or read back.
"""

from __future__ import annotations

import atexit
import json
import os
import pathlib
import threading

#: The folder, where the environment names one.
DIR_ENV = "NLOSJAX_CACHE_DIR"
#: ``"0"`` switches the cache off in every command (as each command's ``--no-cache`` does for one run).
SWITCH_ENV = "NLOSJAX_CACHE"
#: A folder where every counting process writes ``<pid>.json`` at its end (set by the test suite).
COUNTS_ENV = "NLOSJAX_CACHE_COUNTS"

ROOT = pathlib.Path(__file__).resolve().parents[1]
#: Where the folder is in a clone (``.gitignore`` names ``.cache/``) ...
CLONE_DIR = ROOT / ".cache" / "xla"
#: ... and where it is otherwise.
USER_DIR = pathlib.Path("~/.cache/nlosjax/xla")

#: The cache's bound in bytes (least recently read entries are evicted past it). Setting any
#: limit is also what makes JAX lock the folder. Entries are 2 KB to about 0.5 MB on a CPU (the
#: tiny model's init and train step are the large ones).
MAX_SIZE = 2 * 2 ** 30
#: :func:`prune` keeps at most this many entries (the main job and the suite write far fewer each) ...
MAX_ENTRIES = 4000
#: ... and none that no run has read for this many days.
PRUNE_AFTER_DAYS = 7
#: JAX's settings (environment variables, read when JAX is imported), each only where unset:
#: every program is written, however small or quick to compile (the suite's tiny programs
#: compile in 0.1-5 s each, and there are hundreds of them).
SETTINGS = {"JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
            "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES": "0",
            "JAX_COMPILATION_CACHE_MAX_SIZE": str(MAX_SIZE)}

REQUESTS_EVENT = "/jax/compilation_cache/compile_requests_use_cache"
HITS_EVENT = "/jax/compilation_cache/cache_hits"
SAVED_EVENT = "/jax/compilation_cache/compile_time_saved_sec"

_lock = threading.Lock()
_counts = {"requests": 0, "hits": 0, "saved_s": 0.0}
_state: dict = {"listening": False, "at_exit": None, "path": None, "off": None}


def default_dir() -> pathlib.Path:
  """``.cache/xla`` in the clone this module is in, else ``~/.cache/nlosjax/xla``."""
  if (ROOT / "pyproject.toml").is_file() and (ROOT / "experiments").is_dir():
    return CLONE_DIR
  return USER_DIR.expanduser()


def cache_dir(environ=None) -> str | None:
  """The folder the commands use (see the module's docstring), or None where switched off."""
  environ = os.environ if environ is None else environ
  if environ.get(SWITCH_ENV, "1") == "0":
    return None
  return environ.get(DIR_ENV) or environ.get("JAX_COMPILATION_CACHE_DIR") or str(default_dir())


def _have_filelock() -> bool:
  try:
    import filelock  # noqa: F401  (JAX locks the folder with it)
  except ImportError:
    return False
  return True


def configure(environ=None, tidy: bool = False) -> str | None:
  """Make the folder and point JAX at it through ``environ`` (default ``os.environ``).

  Sets ``JAX_COMPILATION_CACHE_DIR`` and ``NLOSJAX_CACHE_DIR`` to the folder and each of
  :data:`SETTINGS` that ``environ`` does not set, so a JAX imported later, and every
  subprocess, uses it. ``tidy``: :func:`prune` the folder first (the main job and the
  suite do; a short command skips the listing). Returns the folder, or None where the cache is off: switched off
  (``NLOSJAX_CACHE=0``), ``filelock`` missing, or the folder cannot be made (the reason
  is kept for :func:`summary`).
  """
  environ = os.environ if environ is None else environ
  path = cache_dir(environ)
  if path is None:
    return _off(f"off ({SWITCH_ENV}=0)")
  if not _have_filelock():
    return _off("off (the filelock package, which JAX locks the folder with, is not installed)")
  try:
    os.makedirs(path, exist_ok=True)
  except OSError as e:
    return _off(f"off (cannot make {path}: {e.strerror})")
  environ["JAX_COMPILATION_CACHE_DIR"] = environ[DIR_ENV] = path
  for key, value in SETTINGS.items():
    environ.setdefault(key, value)
  if tidy:
    prune(path)
  _state.update(path=path, off=None)
  return path


def prune(path, max_entries: int = MAX_ENTRIES, max_age_days: float = PRUNE_AFTER_DAYS,
          now_ns: int | None = None) -> int:
  """Delete entries unread for ``max_age_days``, then the least recently read beyond ``max_entries``.

  Read times are JAX's own (the ``<key>-atime`` file it writes beside each ``<key>-cache``
  on every read and write, where a size limit is set; else the file's time). Deletes under
  JAX's lock of the folder; where the lock is busy for 10 s it deletes nothing. Returns how
  many entries it deleted.
  """
  import time
  folder = pathlib.Path(path)
  now_ns = time.time_ns() if now_ns is None else now_ns
  entries = []                                      # (last read in ns, key)
  try:
    with os.scandir(folder) as it:
      for e in it:
        if not e.name.endswith("-cache"):
          continue
        key = e.name[:-len("-cache")]
        try:
          read = int.from_bytes((folder / f"{key}-atime").read_bytes(), "little")
        except OSError:
          read = e.stat().st_mtime_ns
        entries.append((read, key))
  except OSError:
    return 0
  entries.sort(reverse=True)                        # most recently read first
  cutoff = now_ns - int(max_age_days * 86400e9)
  drop = [key for i, (read, key) in enumerate(entries) if i >= max_entries or read < cutoff]
  if not drop:
    return 0
  import filelock
  try:
    with filelock.FileLock(folder / ".lockfile", timeout=10):   # the lock JAX takes (jax/_src/lru_cache.py)
      for key in drop:
        for suffix in ("-cache", "-atime"):
          try:
            (folder / f"{key}{suffix}").unlink()
          except FileNotFoundError:
            pass
  except (filelock.Timeout, OSError):
    return 0
  return len(drop)


def _off(reason: str) -> None:
  _state.update(path=None, off=reason)
  return None


def enable(environ=None, tidy: bool = False) -> str | None:
  """:func:`configure` (``tidy``: prune first), then the same settings on an imported JAX, and :func:`count`.

  Call it before the process compiles anything: JAX decides at its first compile whether
  the process uses a cache. Returns the folder, or None where the cache is off.
  """
  environ = os.environ if environ is None else environ
  path = configure(environ, tidy=tidy)
  if path is None:
    return None
  import jax
  try:
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs",
                      float(environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes",
                      int(environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"]))
    jax.config.update("jax_compilation_cache_max_size", int(environ["JAX_COMPILATION_CACHE_MAX_SIZE"]))
  except (AttributeError, ValueError) as e:        # an older JAX, or a malformed setting
    return _off(f"off ({e})")
  count()
  return path


#: ``--no-cache``'s help, the same in every command.
NO_CACHE_HELP = ("do not use the persistent XLA compilation cache (NLOSJAX_CACHE_DIR; default .cache/xla"
                 " in a clone of the repository, shared with the main job and the tests, else"
                 " ~/.cache/nlosjax/xla; NLOSJAX_CACHE=0 also switches it off)")


def add_argument(parser) -> None:
  """``--no-cache`` on ``parser`` (an argparse parser or group): one run without the cache."""
  parser.add_argument("--no-cache", action="store_true", help=NO_CACHE_HELP)


def enable_unless(no_cache: bool, tidy: bool = False) -> str | None:
  """:func:`enable` unless ``no_cache`` (a command's ``--no-cache``); the folder, or None."""
  return None if no_cache else enable(tidy=tidy)


# --- The hit rate ---------------------------------------------------------------------------

def _on_event(event: str, **kwargs) -> None:
  if event == REQUESTS_EVENT:
    with _lock:
      _counts["requests"] += 1
  elif event == HITS_EVENT:
    with _lock:
      _counts["hits"] += 1


def _on_duration(event: str, duration: float, **kwargs) -> None:
  if event == SAVED_EVENT:
    with _lock:
      _counts["saved_s"] += float(duration)


def count() -> None:
  """Count this process's compiles through the cache from now on (once per process).

  Where ``NLOSJAX_CACHE_COUNTS`` names a folder, the counts are also written there when
  the process exits (:func:`write_counts`), for the command that started it to add up.
  """
  with _lock:
    if _state["listening"]:
      return
    _state["listening"] = True
  from jax import monitoring
  monitoring.register_event_listener(_on_event)
  monitoring.register_event_duration_secs_listener(_on_duration)
  folder = os.environ.get(COUNTS_ENV)
  if folder and _state["at_exit"] is None:
    _state["at_exit"] = folder
    atexit.register(write_counts, folder)


def counts() -> dict:
  """This process's counts so far: ``requests`` (compiles that asked the cache), ``hits``, ``saved_s``."""
  with _lock:
    return dict(_counts)


def write_counts(folder) -> pathlib.Path | None:
  """Write :func:`counts` to ``<folder>/<pid>.json`` (whole, by a rename); None if the folder is gone."""
  folder = pathlib.Path(folder)
  path = folder / f"{os.getpid()}.json"
  tmp = folder / f".{os.getpid()}.json.tmp"
  try:
    tmp.write_text(json.dumps(counts()))
    os.replace(tmp, path)
  except OSError:
    return None
  return path


def read_counts(folder) -> tuple[dict, int]:
  """The sum of the counts written to ``folder`` and how many processes wrote them."""
  total = {"requests": 0, "hits": 0, "saved_s": 0.0}
  n = 0
  for p in sorted(pathlib.Path(folder).glob("*.json")):
    try:
      one = json.loads(p.read_text())
    except (OSError, ValueError):
      continue
    for key in total:
      total[key] += one.get(key, 0)
    n += 1
  return total, n


def _shown(path: str) -> str:
  """``path`` relative to the working directory where it is inside it."""
  try:
    return os.path.relpath(path) if pathlib.Path(path).resolve().is_relative_to(pathlib.Path.cwd()) else path
  except (OSError, ValueError):
    return path


def summary(totals: dict | None = None, path: str | None = None, where: str = "") -> str:
  """The hit-rate line: ``XLA compilation cache .cache/xla: 57 of 64 compiles read from it (89%), ...``.

  ``totals`` default to this process's :func:`counts`, ``path`` to the folder :func:`configure`
  chose; ``where`` says whose compiles were counted (appended after a comma).
  """
  totals = counts() if totals is None else totals
  path = path or _state["path"]
  if path is None:
    return f"XLA compilation cache: {_state['off'] or 'off'}"
  requests, hits = int(totals["requests"]), int(totals["hits"])
  head = f"XLA compilation cache {_shown(path)}: "
  if not requests:
    line = head + "no compile went through it"
  else:
    line = (head + f"{hits} of {requests} compiles read from it ({100 * hits / requests:.0f}%), "
            f"{max(totals['saved_s'], 0.0):.0f} s of compiling saved")
  return line + (f", {where}" if where else "")
