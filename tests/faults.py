"""Fault injection for the fault campaign (``tests/test_faults.py``): kills, truncation, flipped
bytes, a full disk and read-only folders, each judged the same way.

Every fault ends in one of three outcomes, or the campaign fails:

* ``resumed``: the writer, rerun without the fault, goes on from what survived and ends with
  what an uninterrupted run writes (compared with one, not with itself);
* ``one line``: the reader or writer stops with an error naming the file, what is wrong and
  what to do, on one line, that says the file is damaged (or the disk full, the folder
  read-only): never another cause (:func:`assert_clear`);
* ``no effect``: the fault landed where nothing reads (a flipped byte in unused space), and what
  is read is exactly what was written.

Kills and full disks hit a writer in a child process: :func:`run_child` forks this process
(the child only writes: NumPy, h5py and files, never a JAX computation) and kills it at a
random moment (``SIGKILL``: no ``finally`` runs, nothing is flushed) or runs it under a
file-size limit (``RLIMIT_FSIZE``, so a write past it fails with ``EFBIG`` as on a full disk).
A read-only folder is made read-only with ``chmod``; as root, whom modes do not stop, the child
also drops the capabilities that let root write anyway (:func:`drop_file_privileges`).
Commands that compile run as subprocesses (``run_command``), with ``preexec_fn`` applying the
same limits.

Each injected fault is recorded on the test (``record_property("fault", "artifact|fault|outcome")``);
``conftest.py`` prints the tally at the end of the run.
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import json
import os
import pathlib
import re
import resource
import signal
import stat
import subprocess
import sys
import time
import traceback
import warnings

import numpy as np

#: Outcomes a fault may end in (module docstring).
OUTCOMES = ("resumed", "one line", "no effect")
#: Words one of which a message about a damaged file says (a message saying none of them gives
#: another cause, a wrong diagnosis).
DAMAGE_WORDS = ("damaged", "truncated", "corrupt", "unreadable", "not readable", "cannot be read",
                "does not match", "do not match", "missing", "does not restore", "not a readable")
#: Words of a message about a full disk or a file-size limit.
DISK_WORDS = ("disk is full", "file-size limit")
#: Words of a message about a folder that may not be written.
READ_ONLY_WORDS = ("may not be written", "cannot be opened for writing", "permission denied")
#: Causes a damaged file must never be blamed on.
WRONG_CAUSES = ("locked", "another process", "another model config", "another configuration",
                "another run signature", "trained on data", "not an nlosjax", "interrupted writer")


def record(record_property, artifact: str, fault: str, outcome: str) -> None:
  """Record one injected fault and how it ended (:data:`OUTCOMES`) for the campaign's summary."""
  assert outcome in OUTCOMES, outcome
  record_property("fault", f"{artifact}|{fault}|{outcome}")


def assert_clear(message: str, path, words=DAMAGE_WORDS) -> None:
  """``message`` is one line naming ``path`` (or a file in it), one of ``words``, what to do, and no wrong cause."""
  text = str(message)
  assert "\n" not in text.strip(), f"more than one line: {text!r}"
  assert str(path) in text or pathlib.Path(path).name in text, f"does not name {path}: {text!r}"
  low = text.lower()
  assert any(w in low for w in words), f"does not say what is wrong ({words}): {text!r}"
  assert not any(w in low for w in WRONG_CAUSES), f"a wrong diagnosis: {text!r}"
  assert ";" in text or "rerun" in low or "move" in low, f"does not say what to do: {text!r}"


# ------------------------------------------------------------------ damage
def truncate(path, fraction: float) -> int:
  """Cut ``path`` to ``fraction`` of its size (what a full disk or a crashed machine leaves); returns the size."""
  path = pathlib.Path(path)
  size = int(path.stat().st_size * fraction)
  with open(path, "r+b") as f:
    f.truncate(size)
  return size


def flip(path, rng: np.random.Generator, n: int = 1) -> list[int]:
  """Flip one random bit in each of ``n`` random bytes of ``path``; returns the offsets."""
  path = pathlib.Path(path)
  data = bytearray(path.read_bytes())
  offsets = sorted(int(o) for o in rng.integers(0, len(data), n))
  for o in offsets:
    data[o] ^= 1 << int(rng.integers(8))
  path.write_bytes(bytes(data))
  return offsets


def files_under(folder) -> list[pathlib.Path]:
  """Every file under ``folder``, sorted."""
  return sorted(p for p in pathlib.Path(folder).rglob("*") if p.is_file())


def snapshot(folder) -> dict[str, bytes]:
  """``{relative path: bytes}`` of every file under ``folder`` (to show nothing completed was lost)."""
  folder = pathlib.Path(folder)
  return {str(p.relative_to(folder)): p.read_bytes() for p in files_under(folder)}


@contextlib.contextmanager
def read_only(*folders):
  """Make ``folders`` (not their files) read-only for the block; modes restored after."""
  modes = [(pathlib.Path(f), pathlib.Path(f).stat().st_mode) for f in folders]
  try:
    for f, mode in modes:
      f.chmod(mode & ~(stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))
    yield
  finally:
    for f, mode in modes:
      f.chmod(mode)


# ---------------------------------------------------------------- children
#: Capabilities that let root write where modes say no (DAC_OVERRIDE, DAC_READ_SEARCH, FOWNER).
_FILE_CAPS = (1, 2, 3)


def drop_file_privileges() -> None:
  """Make this process (and what it executes) obey file modes even as root; nothing to do otherwise."""
  if os.geteuid() != 0:
    return
  libc = ctypes.CDLL(None, use_errno=True)
  for cap in _FILE_CAPS:                       # from the bounding set: gone after an exec too
    libc.prctl(24, cap, 0, 0, 0)               # PR_CAPBSET_DROP

  class Header(ctypes.Structure):
    _fields_ = [("version", ctypes.c_uint32), ("pid", ctypes.c_int)]

  class Data(ctypes.Structure):
    _fields_ = [("effective", ctypes.c_uint32), ("permitted", ctypes.c_uint32),
                ("inheritable", ctypes.c_uint32)]

  header, data = Header(0x20080522, 0), (Data * 2)()
  if libc.capget(ctypes.byref(header), data) != 0:
    raise OSError(ctypes.get_errno(), "capget failed")
  mask = ~sum(1 << c for c in _FILE_CAPS) & 0xFFFFFFFF
  data[0].effective &= mask
  data[0].permitted &= mask
  if libc.capset(ctypes.byref(header), data) != 0:
    raise OSError(ctypes.get_errno(), "capset failed")


def limits(fsize: int | None = None, read_only: bool = False):
  """A ``preexec_fn`` (or a child's first call): a file-size limit of ``fsize`` bytes, file modes obeyed."""
  def apply():
    if fsize is not None:
      resource.setrlimit(resource.RLIMIT_FSIZE, (int(fsize), int(fsize)))
    if read_only:
      drop_file_privileges()
  return apply


@dataclasses.dataclass
class Child:
  """How a child ended: ``killed`` (by the campaign's ``SIGKILL``), or its ``error`` (type, message) or None."""

  killed: bool
  error: tuple[str, str] | None
  seconds: float


def run_child(fn, *, kill_after: float | None = None, fsize: int | None = None,
              read_only: bool = False, timeout: float = 120.0) -> Child:
  """Run ``fn()`` in a forked child: killed after ``kill_after`` seconds, or under the limits.

  The child only writes files (no JAX computation: a forked JAX is not safe to compute in).
  Returns how it ended; an exception in the child comes back as ``(type name, message)``.
  """
  read_end, write_end = os.pipe()
  with warnings.catch_warnings():          # JAX warns that fork and threads do not mix: the child computes nothing
    warnings.simplefilter("ignore")
    t0 = time.perf_counter()
    pid = os.fork()
  if pid == 0:                             # the child
    os.close(read_end)
    code, out = 0, {"error": None}
    try:
      limits(fsize, read_only)()
      fn()
    except BaseException as e:  # noqa: BLE001 - every outcome goes back to the parent
      out = {"error": [type(e).__name__, str(e)], "traceback": traceback.format_exc()}
      code = 1
    try:
      os.write(write_end, json.dumps(out).encode())
    finally:
      os._exit(code)
  os.close(write_end)
  killed = False
  status = None
  if kill_after is not None:
    deadline = time.perf_counter() + kill_after
    while time.perf_counter() < deadline:
      done, st = os.waitpid(pid, os.WNOHANG)
      if done:
        status = st
        break
      time.sleep(min(0.002, max(0.0, deadline - time.perf_counter())))
    else:
      os.kill(pid, signal.SIGKILL)
      killed = True
  end = time.perf_counter() + timeout
  while status is None:
    done, st = os.waitpid(pid, os.WNOHANG)
    if done:
      status = st
    elif time.perf_counter() > end:
      os.kill(pid, signal.SIGKILL)
      os.waitpid(pid, 0)
      raise TimeoutError(f"child {pid} ran past {timeout} s")
    else:
      time.sleep(0.002)
  with os.fdopen(read_end, "rb") as f:
    data = f.read()
  seconds = time.perf_counter() - t0
  if killed and os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL:
    return Child(killed=True, error=None, seconds=seconds)
  info = json.loads(data) if data else {"error": ["died", f"status {status}"]}
  return Child(killed=killed, error=None if info["error"] is None else tuple(info["error"]), seconds=seconds)


def duration(fn, runs: int = 3) -> float:
  """Seconds ``fn`` takes in a child, start to end (the least of ``runs``: the first warms up)."""
  times = []
  for _ in range(runs):
    child = run_child(fn)
    assert child.error is None, child.error
    times.append(child.seconds)
  return min(times)


def kill_times(rng: np.random.Generator, duration: float, n: int) -> list[float]:
  """``n`` kill moments spread over ``[0, duration]`` (stratified: one in each of ``n`` slices)."""
  return [float((i + rng.random()) * duration / n) for i in range(n)]


# ---------------------------------------------------------------- commands
@dataclasses.dataclass
class Result:
  """A command's exit status and output."""

  returncode: int
  stdout: str
  stderr: str


def run_command(module: str, *args, cwd=None, env=None, fsize: int | None = None,
                read_only: bool = False, kill_after: float | None = None,
                kill_when=None, timeout: float = 900.0) -> Result:
  """``python -m module args`` with this repository importable, optionally limited, or killed.

  ``kill_after``: ``SIGKILL`` after that many seconds; ``kill_when``: a function of the output so far
  (stdout and stderr) that returns True when the process is to be killed.
  """
  root = pathlib.Path(__file__).resolve().parents[1]
  environ = {**os.environ, **(env or {})}
  environ["PYTHONPATH"] = os.pathsep.join([str(root), *filter(None, [environ.get("PYTHONPATH")])])
  with warnings.catch_warnings():   # JAX warns at every fork (preexec_fn forks): the child execs at once
    warnings.simplefilter("ignore")
    proc = subprocess.Popen([sys.executable, "-m", module, *map(str, args)], cwd=cwd, env=environ,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT if kill_when else subprocess.PIPE,
                            text=True, preexec_fn=limits(fsize, read_only))
  if kill_when is None and kill_after is None:
    out, err = proc.communicate(timeout=timeout)
    return Result(proc.returncode, out, err)
  import selectors
  seen, t0 = [], time.perf_counter()
  sel = selectors.DefaultSelector()
  streams = [proc.stdout] + ([proc.stderr] if proc.stderr else [])
  for s in streams:
    os.set_blocking(s.fileno(), False)
    sel.register(s, selectors.EVENT_READ)
  while proc.poll() is None:
    for key, _ in sel.select(timeout=0.05):
      chunk = key.fileobj.read()
      if chunk:
        seen.append(chunk)
    text = "".join(seen)
    if (kill_when is not None and kill_when(text)) or (
        kill_after is not None and time.perf_counter() - t0 > kill_after):
      proc.kill()
      break
    if time.perf_counter() - t0 > timeout:
      proc.kill()
      raise TimeoutError(f"python -m {module} ran past {timeout} s")
  proc.wait()
  for s in streams:
    with contextlib.suppress(TypeError, OSError):
      rest = s.read()
      if rest:
        seen.append(rest)
    s.close()
  sel.close()
  return Result(proc.returncode, "".join(seen), "")


def error_lines(stderr: str) -> list[str]:
  """What a command told the user on stderr: its non-empty lines, progress bars left out."""
  lines = []
  for line in stderr.replace("\r", "\n").splitlines():
    line = line.strip()
    if line and not re.match(r"^(train|writing|evaluating|validating|tuning|scoring)\b.*\|", line) \
        and "%|" not in line:
      lines.append(line)
  return lines


# ----------------------------------------------------------------- summary
def summary(reports) -> list[str]:
  """The campaign's tally from pytest's test reports: faults injected, survived, and how, by artifact and fault.

  A fault survived when its test passed (``record`` comes before the test's later checks, so a
  failure after it counts its faults as not survived).
  """
  rows: dict[tuple[str, str], dict[str, int]] = {}
  lost = 0
  for report in reports:
    if getattr(report, "when", None) != "call":
      continue
    for name, value in getattr(report, "user_properties", ()):
      if name != "fault":
        continue
      artifact, fault, outcome = str(value).split("|")
      row = rows.setdefault((artifact, fault), {})
      key = outcome if report.passed else "not survived"
      row[key] = row.get(key, 0) + 1
      lost += not report.passed
  if not rows:
    return []
  total = sum(sum(r.values()) for r in rows.values())
  how = {o: sum(r.get(o, 0) for r in rows.values()) for o in OUTCOMES}
  lines = [f"fault campaign: {total} faults injected, {total - lost} survived ("
           + ", ".join(f"{o} {n}" for o, n in how.items() if n) + f"), {lost} not"]
  for artifact in sorted({a for a, _ in rows}):
    parts = []
    for (a, fault), row in sorted(rows.items()):
      if a == artifact:
        parts.append(f"{fault} {sum(row.values())} ("
                     + ", ".join(f"{k} {v}" for k, v in sorted(row.items())) + ")")
    lines.append(f"  {artifact}: " + "; ".join(parts))
  return lines
