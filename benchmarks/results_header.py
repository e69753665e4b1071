"""What a results file's header says, and a module's code at a commit: read by the index and the equivalence check.

:func:`read_entry` parses the provenance lines every results file starts with (the
command that wrote it, date, machine, commit, and its code digest with the modules it
covers); :class:`GitFiles` reads files at commits through one ``git cat-file`` process;
:func:`same_code` compares two versions of a module as the code digest does (comments
and docstrings aside). Both :mod:`benchmarks.index` and :mod:`benchmarks.equivalence`
import from here, so neither imports the other for them. :func:`results_folders` lists where
results files live: ``benchmarks/results/`` (performance) and each study's ``results/``.
"""

from __future__ import annotations

import dataclasses
import pathlib
import re
import subprocess

from experiments import provenance


@dataclasses.dataclass(frozen=True)
class Entry:
  """One results file's provenance, as its header states it."""
  name: str           # file stem, e.g. "table1"
  title: str
  command: str
  date: str
  machine: str
  commit: str
  digest: str = ""                  # the "- Code: `...`" digest, or "" where the file has none
  modules: tuple[str, ...] = ()     # the modules that digest covers
  path: pathlib.Path | None = dataclasses.field(default=None, compare=False)   # the file read


def results_folders(root: pathlib.Path | None = None) -> list[pathlib.Path]:
  """Every folder of results files under ``root`` (default: this checkout): ``benchmarks/results``,
  then ``experiments/studies/<study>/results`` by study name."""
  root = provenance.ROOT if root is None else pathlib.Path(root)
  return [root / "benchmarks" / "results", *sorted((root / "experiments" / "studies").glob("*/results"))]


def _first(pattern: str, text: str, default: str = "?") -> str:
  m = re.search(pattern, text, flags=re.MULTILINE)
  return m.group(1).strip() if m else default


def read_entry(path: pathlib.Path) -> Entry:
  """Parse the header of one results Markdown file.

  Raises:
    ValueError: the file names no "Produced by `...`" command.
  """
  text = path.read_text()
  body = "\n".join(line for line in text.splitlines() if not line.startswith(">"))
  command = _first(r"Produced by `([^`]+)`", body, "")
  if not command:
    raise ValueError(f"{path.name} does not say which command produced it ('Produced by `...`')")
  date = _first(r"^- Date: (\S+)", body, "")
  if not date:
    date = _first(r"Produced by `[^`]+` on (\S+?)[ .(]", body)
  machine = _first(r"^- (?:Machine|CPU): ([^;\n]+)", body)
  commit = _first(r"^- Commit: (.+)$", body)
  code = provenance.CODE_LINE.search(body)
  return Entry(path.stem, _first(r"^# (.+)$", body), command, date, machine, commit,
               code.group(1) if code else "", tuple(code.group(2).split()) if code else (), path)


def git_output(*args: str) -> str | None:
  """``git args`` in the repository; its stripped output, or None where git fails."""
  try:
    return subprocess.run(["git", *args], cwd=provenance.ROOT, check=True, capture_output=True,
                          text=True).stdout.strip()
  except (OSError, subprocess.CalledProcessError):
    return None


class GitFiles:
  """Files at commits, read through one ``git cat-file --batch`` process (None where absent)."""

  def __init__(self):
    self._proc = None
    self._cache: dict[str, str | None] = {}

  def __call__(self, commit: str, path: str) -> str | None:
    key = f"{commit}:{path}"
    if key not in self._cache:
      if self._proc is None:
        self._proc = subprocess.Popen(["git", "cat-file", "--batch"], cwd=provenance.ROOT,
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE)
      self._proc.stdin.write(key.encode() + b"\n")
      self._proc.stdin.flush()
      header = self._proc.stdout.readline().split()
      if len(header) == 3:
        data = self._proc.stdout.read(int(header[2]))
        self._proc.stdout.read(1)
        self._cache[key] = data.decode()
      else:
        self._cache[key] = None                    # "<key> missing"
    return self._cache[key]

  def close(self):
    if self._proc is not None:
      self._proc.stdin.close()
      self._proc.wait()
      self._proc = None


def same_code(a: str | None, b: str | None, path: str) -> bool:
  """Whether two versions of a module hold the same code (comments and docstrings aside)."""
  if a is None or b is None:
    return a is b
  try:
    return provenance._behaviour(a, path) == provenance._behaviour(b, path)
  except SyntaxError:
    return a == b
