"""Write ``benchmarks/README.md``, the index of every results file, from the results files' headers.

    python -m benchmarks.index                  # rewrite benchmarks/README.md
    python -m benchmarks.index --check          # exit 1 if it differs from what the files say
    python -m benchmarks.index --touched REV    # the results files a change since REV can move

Results files live in ``benchmarks/results/`` (performance) and in each study's own
``experiments/studies/<study>/results/`` (:func:`results_folders`). Each row is read from one
file's header: its title, the command that wrote it ("Produced by `...`"), its date, machine
and commit. Nothing here is typed by hand but the goal each file is judged against
(:data:`GOALS`). A results file is regenerated, by its own command, when a change can move its
numbers: :func:`touched` lists the files whose command imports a module whose code (not its
comments or docstrings) changed since a commit; the golden tests (``tests/golden``) say
whether numbers moved at all.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import os
import pathlib
import re
import subprocess
import sys

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent
RESULTS = HERE / "results"
INDEX = HERE / "README.md"
#: The project's packages: the import closure of a command stays inside them.
PACKAGES = ("nlosjax", "experiments", "benchmarks")

# What each results file is judged against (the goal its benchmark was written for); a file not
# named here shows "none stated".
GOALS = {
    "compile": "the paper-scale physics operators passed as arguments, not baked in as constants: "
               "smaller programs, faster compiles, the same numbers",
    "data": "near-linear speed-up with `--workers`",
    "device": "paper-scale inference >= 30 frames/s on one H100; dry-run memory within ±20 % of the measured "
              "peak; scan fwd+bwd <= 6x the exp floor; auto within 10 % of the best; every correctness check "
              "passes",
    "dry_run": "refuses a run above 90 % of device memory",
    "headroom": "know the headroom on the objects: every method's object scores beside what the 8 x 8 input "
                "supports (the truth at its scan points; the reference classic method fed noise-free and full-scan "
                "inputs), by object size, depth, photons and motion, on the test split, the independent set and the "
                "held-out renderer",
    "hlo_gpu_compiled": "on the `paper` train step compiled for an H200 without a GPU: no cuDNN convolution with a "
                        "window larger than 3 x 3 (every weight gradient backward-filter), no float atomics, no FFT "
                        "length with a prime factor above 7, no FFT inside a loop, roofline under 0.5 s a step",
    "main_job": "the main job within 1200 s (20 min on 2 cores)",
    "mechanisms": "full - no-SSM and full - Ours-S with intervals at both photon budgets, every run "
                  "trained to its validation plateau; the SSM probe of a trained Ours",
    "mitransient": "the shipped `cpu` networks and the five classic methods on the preset's test scenes "
                   "rendered by a path tracer we did not write, the object scores first, every choice on "
                   "validation; what the path tracer adds and what the scenes still leave out named",
    "objects": "on the cpu test split, the independent set and the held-out renderer: Ours' object intensity "
               "error below every classic method's, object recall at least the best classic's and surface F1 "
               "above it (95 % intervals over sequences and 3 seeds excluding 0); intensity PSNR >= 3 dB above "
               "the all-zero image and the best classic method",
    "objects_screen": "each recipe of the cpu preset scored on the validation objects; the preset's default "
                      "chosen there",
    "physics": "each method <= 1.3x its FFT floor and >= 1x the same-variant NumPy/SciPy twin, "
               "at 64² and 128²",
    "physics_shift": "on every renderer family left out of training: Ours >= best classic + 1 dB, object "
                     "recall >= the best classic's, Ours >= Ours-S",
    "real": "the network ahead of every method without training (the classic ones and CSA) against every"
            " other method's full scan",
    "real_public": "a network whose physics layer has the public operators, beside the refined one it "
                   "would replace, on the measured scans",
    "real_adapt": "each network fitted to each scan never worse on average than as trained; ahead of "
                  "every method without training (the classic ones and CSA)",
    "csa_choice": "CSA's prior weight chosen per stride on simulated validation sequences, never on measured"
                  " scans",
    "realism": "a classifier tells measured from simulated inputs in <= 60 % of held-out cases",
    "realism_v4": "a classifier tells measured from simulated inputs in <= 60 % of held-out cases",
    "realism_v5": "a classifier tells measured from simulated inputs in <= 60 % of held-out cases",
    "reconstruct_time": "`experiments.reconstruct` with the shipped model on a 64 x 64 x 512 capture in "
                        "under 10 s on 2 cores, compile included",
    "scan": "associative <= 4x / <= 10x the exp floor (forward / fwd+bwd), best <= 2x / <= 6x, "
            "auto within 10 % of the best, fwd+bwd peak <= 3x inputs + outputs",
    "scan_torch": "associative >= 5x faster than mambapy's pscan, fwd+bwd",
    "stopping_replay": "time to the validation plateau halved by a stopping rule that keeps the "
                       "best validation score",
    "table1": "Ours - Ours-S >= +0.5 dB; Ours >= best classic + 3 dB; "
              "Ours >= USM + 0.5 dB",
    "table1_independent": "Ours >= best classic + 1 dB, recall >= 0.85",
    "table1_low_photon": "Ours - Ours-S >= +0.5 dB where photons are scarce",
    "table2_controls": "full - no-SSM >= +1 dB",
    "table2_controls_low_photon": "full - no-SSM >= +1 dB where photons are scarce",
    "tradeoff": "halving the depth range cuts LCT and network time by >= 1.6x",
}

HEADER = """# Benchmarks and studies: an index of every results file

Each benchmark measures its candidates and what they are judged against (FFT floors, exp floors,
NumPy/SciPy twins, the full model) side by side in one run and prints ratios, since absolute
times on a shared machine move between runs. Performance results live in `results/`; each study
of `experiments/studies/` keeps its own in its `results/` folder, beside its code and committed
run states. Each results file is written whole by the command named in its first lines
("Produced by `...`"), with the date, the machine and the commit it ran at; the numbers are in
the files, and the README and `docs/` quote them with that commit. A file is regenerated with
its command when a change can move its numbers: `python -m benchmarks.index --touched REV` lists
the files whose command runs code changed since `REV`, and the golden tests
(`python -m tests.golden`) say whether any number moved. Documentation, comments and help strings
move none. Where a study or its results have moved since a file was written, the command column
gives the command as typed today and the one that ran. Files a later study supersedes are kept,
unindexed, in `experiments/studies/archive/`, whose README names what replaces each.
`pip install -e ".[bench]"` installs PyTorch and mambapy, needed only for
`benchmarks/scan_torch.py`. Imports run downward only: `nlosjax` <- `experiments` (the application,
then its studies) <- `benchmarks` (provenance and the NumPy twins live in `experiments/`).

This file is written by `python -m benchmarks.index` from the results files' headers; rerun it
after any benchmark (a test fails while it is out of date).

**On a GPU** (`device.md`): see `docs/gpu.md`; `python -m benchmarks.device --tiny` rehearses
the device command's code paths on CPU in the test suite, so it cannot break unnoticed between
GPU runs.
"""


@dataclasses.dataclass(frozen=True)
class Entry:
  """One results file's provenance, as its header states it."""
  name: str           # file stem, e.g. "table1"
  title: str
  command: str
  date: str
  machine: str
  commit: str
  path: pathlib.Path | None = dataclasses.field(default=None, compare=False)   # the file read


def results_folders(root: pathlib.Path | None = None) -> list[pathlib.Path]:
  """Every folder of results files under ``root`` (default: this checkout): ``benchmarks/results``,
  then ``experiments/studies/<study>/results`` by study name."""
  root = ROOT if root is None else pathlib.Path(root)
  return [root / "benchmarks" / "results", *sorted((root / "experiments" / "studies").glob("*/results"))]


def _first(pattern: str, text: str, default: str = "?") -> str:
  m = re.search(pattern, text, flags=re.MULTILINE)
  return m.group(1).strip() if m else default


def read_entry(path: pathlib.Path) -> Entry:
  """Parse the header of one results Markdown file.

  Raises:
    ValueError: the file names no "Produced by `...`" command.
  """
  body = "\n".join(line for line in path.read_text().splitlines() if not line.startswith(">"))
  command = _first(r"Produced by `([^`]+)`", body, "")
  if not command:
    raise ValueError(f"{path.name} does not say which command produced it ('Produced by `...`')")
  date = _first(r"^- Date: (\S+)", body, "") or _first(r"Produced by `[^`]+` on (\S+?)[ .(]", body)
  return Entry(path.stem, _first(r"^# (.+)$", body), command, date, _first(r"^- (?:Machine|CPU): ([^;\n]+)", body),
               _first(r"^- Commit: (.+)$", body), path)


def entries(results: pathlib.Path | None = None) -> list[Entry]:
  """Every ``*.md`` results file of ``results`` (default: every folder of :func:`results_folders`), by name.

  Raises:
    ValueError: two folders hold results files of the same name (a name must say which file).
  """
  folders = results_folders() if results is None else [pathlib.Path(results)]
  found = sorted((read_entry(p) for f in folders for p in f.glob("*.md")), key=lambda e: e.name)
  twice = sorted({a.name for a, b in zip(found, found[1:]) if a.name == b.name})
  if twice:
    raise ValueError(f"results files named twice: {', '.join(twice)} (a name must say which file)")
  return found


def _owner(stem: str, tables) -> str | None:
  """The results table a file named ``stem`` belongs to: the longest table name it is or starts with."""
  return max((t for t in tables if stem == t or stem.startswith(t + "_")), key=len, default=None)


def companions(results: pathlib.Path, stem: str, tables: set[str] | None = None) -> list[str]:
  """Other files of ``results`` whose names start with ``stem`` (figures, JSON), not other tables.

  ``tables``: the stems of every results table (read from ``results`` when not given).
  """
  tables = {p.stem for p in results.glob("*.md")} if tables is None else tables
  return [p.name for p in sorted(results.iterdir())
          if p.suffix != ".md" and p.name.startswith(stem) and _owner(p.stem, tables) == stem]


def as_typed_today(command: str, found: list[Entry]) -> str:
  """``command`` as typed today: a module that moved into ``experiments/studies/`` named where it
  lives, and each ``benchmarks/results/<file>`` it writes that lives in a study's folder today
  at today's path."""
  def module(m: re.Match) -> str:
    name = m.group(1)
    if _module_path(name) is None and _module_path(f"experiments.studies.{name.rsplit('.', 1)[-1]}"):
      return f"-m experiments.studies.{name.rsplit('.', 1)[-1]}"
    return m.group(0)
  where = {e.name: e.path.parent for e in found}

  def output(m: re.Match) -> str:
    stem = _owner(m.group(1), where)
    if stem is None or where[stem] == RESULTS:
      return m.group(0)
    return (where[stem] / m.group(1)).relative_to(ROOT).as_posix() + m.group(2)
  command = re.sub(r"-m ((?:benchmarks|experiments)(?:\.\w+)+)", module, command)
  return re.sub(r"benchmarks/results/([A-Za-z0-9_]+)(\.\w+)", output, command)


def render(results: pathlib.Path | None = None) -> str:
  """The index's Markdown text."""
  lines = [HEADER, "| results file | what | command | date (UTC) | machine | commit | goal | companions |",
           "|---|---|---|---|---|---|---|---|"]
  found = entries(results)
  tables = {e.name for e in found}
  for e in found:
    today = as_typed_today(e.command, found)
    command = f"`{today}`" + ("" if today == e.command else f" (ran as `{e.command}`)")
    link = pathlib.Path(os.path.relpath(e.path, HERE)).as_posix()
    cells = [f"[{e.name}.md]({link})", e.title, command, e.date, e.machine, e.commit,
             GOALS.get(e.name, "none stated"), ", ".join(companions(e.path.parent, e.name, tables))]
    lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
  return "\n".join(lines) + "\n"


# --- Which results files a change can move: the static import closure of each file's command ----------

def _module_path(name: str, root: pathlib.Path | None = None) -> str | None:
  """Repository-relative path of project module ``name`` (``a/b.py`` or ``a/b/__init__.py``), or None."""
  root = ROOT if root is None else root
  if name.split(".")[0] not in PACKAGES:
    return None
  base = name.replace(".", "/")
  for candidate in (base + ".py", base + "/__init__.py"):
    if (root / candidate).is_file():
      return candidate
  return None


def _imports(path: str, root: pathlib.Path) -> set[str]:
  """Every module name ``path``'s code may import (function-level imports too; ``from a import b``
  yields ``a`` and ``a.b``; a run-time ``import_module`` name: any module beside it)."""
  package = path[:-len("/__init__.py")] if path.endswith("/__init__.py") else path.rsplit("/", 1)[0]
  package = package.replace("/", ".")
  names = set()
  for node in ast.walk(ast.parse((root / path).read_text(), filename=path)):
    if isinstance(node, ast.Import):
      names.update(alias.name for alias in node.names)
    elif isinstance(node, ast.ImportFrom):
      base = package.split(".")[:len(package.split(".")) - node.level + 1] if node.level else []
      mod = ".".join(base + ([node.module] if node.module else []))
      names.add(mod)
      names.update(f"{mod}.{alias.name}" for alias in node.names)
    elif isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "import_module" and node.args:
      folder = root / package.replace(".", "/")
      names.update(f"{package}.{p.stem}" for p in folder.glob("*.py"))
  return names


def code_closure(roots, root: pathlib.Path | None = None) -> set[str]:
  """The project files that modules ``roots`` may run: their imports, transitively, with each
  module's enclosing packages' ``__init__.py`` (a superset of what one run loads)."""
  root = ROOT if root is None else root
  todo, seen = list(roots), set()
  while todo:
    parts = todo.pop().split(".")
    for i in range(1, len(parts) + 1):              # importing a.b.c runs a and a.b first
      path = _module_path(".".join(parts[:i]), root)
      if path is not None and path not in seen:
        seen.add(path)
        todo.extend(_imports(path, root))
  return seen


def _code(source: str | None) -> str | None:
  """``source``'s syntax tree without docstrings, as text (comments and layout never count)."""
  if source is None:
    return None
  try:
    tree = ast.parse(source)
  except SyntaxError:
    return source
  for node in ast.walk(tree):
    body = getattr(node, "body", None)
    if (isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and body
        and isinstance(body[0], ast.Expr) and isinstance(getattr(body[0], "value", None), ast.Constant)
        and isinstance(body[0].value.value, str)):
      node.body = body[1:] or [ast.Pass()]
  return ast.dump(tree)


def changed_code(since: str = "HEAD") -> set[str]:
  """Project ``.py`` files whose code (not comments or docstrings) differs from commit ``since``."""
  def git(*args):
    return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True)
  listed = git("diff", "--name-only", since, "--", *PACKAGES).stdout.split()
  listed += git("ls-files", "--others", "--exclude-standard", "--", *PACKAGES).stdout.split()
  out = set()
  for path in (p for p in listed if p.endswith(".py")):
    before = git("show", f"{since}:{path}")
    now = (ROOT / path).read_text() if (ROOT / path).exists() else None
    if _code(before.stdout if before.returncode == 0 else None) != _code(now):
      out.add(path)
  return out


def command_modules(command: str) -> list[str]:
  """The project modules a results file's command starts (``python -m pkg.mod ...``: both the
  package and its ``__main__``); the main job's benchmark also starts the main job."""
  m = re.search(r"-m ((?:benchmarks|experiments)(?:\.\w+)+)", command)
  if not m:
    return []
  name = m.group(1)
  mods = [name, f"{name}.__main__"]
  if name == "benchmarks.main_job":
    mods += ["experiments.train"]
  return mods


def touched(since: str = "HEAD") -> list[str]:
  """Results files (by path) whose command may run code changed since ``since``."""
  changed = changed_code(since)
  if not changed:
    return []
  found = entries()
  return [e.path.relative_to(ROOT).as_posix() for e in found
          if changed & code_closure(command_modules(as_typed_today(e.command, found)))]


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--check", action="store_true", help="exit 1 if benchmarks/README.md is out of date")
  p.add_argument("--touched", metavar="REV", help="list the results files a change since REV can move")
  args = p.parse_args(argv)
  if args.touched:
    for path in touched(args.touched):
      print(path)
    return 0
  text = render()
  if args.check:
    if INDEX.read_text() != text:
      print("benchmarks/README.md is out of date: run python -m benchmarks.index", file=sys.stderr)
      return 1
    return 0
  INDEX.write_text(text)
  print(f"wrote {INDEX}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
