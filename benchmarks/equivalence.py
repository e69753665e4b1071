"""Results carried forward: does a code change move any number the results files are made of?

    python -m benchmarks.equivalence --base COMMIT [COMMIT ...] [--out FILE ...] [--probe measured|studies|scripts]

Runs the fixed probes of :mod:`benchmarks.equivalence_probe` (tiny datasets of every
renderer family, three train steps of Ours-S, Ours and USM, the evaluation protocol,
every shipped network on a fixed input, every classic reconstruction) twice, side by
side: on ``COMMIT``'s tree (a temporary ``git worktree``) and on today's, and compares
every array: the largest difference relative to the largest magnitude of the earlier
value, against :data:`TOLERANCE` (float32 rounding over a few operations, far below any
difference a results file reports). Writes ``equivalence.md`` and ``equivalence.json``.

How ``python -m benchmarks.index`` uses it (:func:`carried_forward`): a results file
that is stale today is **carried forward** when this file is current, every probe
passed, the results file was current at ``COMMIT`` (its code digest recomputed on that
commit's files), and every module of the file whose code changed since ``COMMIT`` lies
in this command's own import closure (the code the probes ran), or in the union of the
closures of the records against ``COMMIT`` (below). A record that compared no array at all
fails. The numbers stay the
ones measured, with their commit; the index names this check beside them. A change that
moves a probe beyond the tolerance carries nothing: those files are regenerated, or a
study's seed is retrained at the new code and shown to land inside its interval.

Blind spot: the probes shrink each preset to tiny sizes and fix its training settings, so
a change to a preset's own values (a learning rate, a step count) moves no probe; whoever
changes a preset regenerates the files that run it rather than relying on this check
(``main_job.md`` after the ``cpu`` preset's schedule changed in 7e438ba).

A module moved verbatim (:data:`MOVES`) is judged at its new path: a results file naming
the old path compares the base's code with today's at the new one, and every import of the
old dotted name, written with the new name, counts as the same code; so does a function or
class renamed everywhere (:data:`RENAMED`).

``--probe measured`` runs :mod:`benchmarks.equivalence_probe_measured` instead (the
measured-scan protocol's command line, end to end on a small scan) and writes records of its
own (``equivalence_measured.md``, ``equivalence_measured_<COMMIT>.md``): its closure holds the
protocol, so a results file of the protocol is carried by one of them, alone or with the main
record against the same base. A base without the protocol writes no array, and its measured
record fails; any failed record stops its base from carrying anything.

The rule chains: a results file that ``COMMIT``'s own committed index showed as carried
forward, and that is byte for byte the file ``COMMIT`` held, is carried on by records against
``COMMIT`` that cover the changes since (:func:`_carried_at`). So records against the last
landed commit carry every file that commit's index carried, and no older base need be rerun.

``--probe studies`` runs :mod:`benchmarks.equivalence_probe_studies` (studies' own code between
their designs and the library, at tiny sizes: the mechanisms study's ``--tiny`` run, the
speed-accuracy study's training) and writes ``equivalence_studies.md``; its closure holds those
studies' modules, so a change to how a study builds, trains and records its runs can be carried.
Its blind spot is the main probe's, wider: a study's lines only its full design runs (the
mechanisms CLI's config assembly outside ``--tiny``) are in the closure but not run.

``--probe scripts`` runs :mod:`benchmarks.equivalence_probe_scripts` (the performance
benchmarks' own code on a tiny preset: the fingerprints of the programs they time and every
number that is not a time; and the studies the studies probe leaves out: preset choice,
independent test, generalisation, the weights export, time to plateau, the real-preset
runs, alignment, realism) and writes ``equivalence_scripts.md``. A performance file is
carried when the programs it times are unchanged: the same lowered text, the same model
config.

Records against several bases may stand side by side (``equivalence.md`` for the first
base named, ``equivalence_<COMMIT>.md`` for the others; :func:`records`): a file is carried
when the records against one base carry it, so files current at different commits can all be
carried.
Today's probe runs once for all the bases.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import re
import subprocess
import sys
import tempfile
import time

import numpy as np

from experiments import provenance

HERE = pathlib.Path(__file__).resolve().parent
PROBE = HERE / "equivalence_probe.py"
#: The probe scripts by ``--probe`` name: ``main`` (the library, the main job, the shipped
#: networks), ``measured`` (the measured-scan protocol's command line on a small scan,
#: :mod:`benchmarks.equivalence_probe_measured`), ``studies`` (the studies' own paths at tiny
#: sizes, :mod:`benchmarks.equivalence_probe_studies`), ``scripts`` (the performance benchmarks'
#: programs and the other studies' paths, :mod:`benchmarks.equivalence_probe_scripts`), each with
#: records of its own.
PROBES = {"main": PROBE, "measured": HERE / "equivalence_probe_measured.py",
          "studies": HERE / "equivalence_probe_studies.py", "scripts": HERE / "equivalence_probe_scripts.py"}
#: Largest ``max|new - old| / max|old|`` of one probe array that counts as rounding.
TOLERANCE = 1e-5
NAME = "equivalence"
#: Modules and folders moved since a base, old path -> new path (a folder ends in ``/``): the
#: library's application and study instruments moved out of ``nlosjax``, the studies out of
#: ``benchmarks``, then each single-file study into a folder of its own (its ``__init__.py``).
#: Only code moved unchanged belongs here (a moved module whose code changed too counts as changed).
MOVES = {
    "nlosjax/main_job.py": "experiments/main_job.py",
    "nlosjax/models/probe.py": "experiments/studies/mechanisms/probe.py",
    "nlosjax/train/align.py": "experiments/studies/alignment.py",
    "experiments/alignment.py": "experiments/studies/alignment.py",
    "experiments/align.py": "experiments/studies/align.py",
    "experiments/real_undersampling/": "experiments/studies/real_undersampling/",
    **{f"benchmarks/{name}/": f"experiments/studies/{name}/" for name in ("mechanisms", "physics_shift")},
    **{f"benchmarks/{name}.py": f"experiments/studies/{name}/__init__.py"
       for name in ("generalisation", "realism", "ablations", "preset_choice", "time_to_plateau",
                    "stopping_replay", "independent_test", "temporal_probe")},
    **{f"experiments/studies/{name}.py": f"experiments/studies/{name}/__init__.py"
       for name in ("generalisation", "realism", "ablations", "preset_choice", "time_to_plateau",
                    "stopping_replay", "independent_test", "temporal_probe", "table1")},
}

#: Functions and classes renamed since a base, old name -> new name (whole words; names
#: distinctive enough that no other identifier or text spells them).
RENAMED = {
    "adapt_to_capture": "for_capture",
    "CaptureAdaptation": "CaptureView",
}


def _dotted(path: str) -> str:
  """The module name of a file or folder path (a package's ``__init__.py`` is the package)."""
  return path.removesuffix("/").removesuffix(".py").removesuffix("/__init__").replace("/", ".")


def moved_path(path: str) -> str:
  """Where the module at ``path`` (as a base commit names it) lies today (:data:`MOVES`)."""
  for old, new in MOVES.items():
    if path == old or (old.endswith("/") and path.startswith(old)):
      return new + path[len(old):]
  return path


def as_moved(source: str | None) -> str | None:
  """``source`` with every name of a moved module or folder of :data:`MOVES` written with its new
  one (imports, dotted names in text such as ``python -m`` commands, and file paths), and every
  name of :data:`RENAMED` with its new one."""
  if source is None:
    return None
  for old, new in RENAMED.items():
    source = re.sub(rf"\b{re.escape(old)}\b", new, source)
  for old, new in MOVES.items():
    (old_pkg, old_name), (new_pkg, new_name) = _dotted(old).rsplit(".", 1), _dotted(new).rsplit(".", 1)
    source = re.sub(rf"\bfrom {re.escape(old_pkg)} import {old_name}\b", f"from {new_pkg} import {new_name}", source)
    source = re.sub(rf"\b{re.escape(_dotted(old))}\b", _dotted(new), source)
    if old.endswith("/"):
      source = re.sub(rf"\b{re.escape(old)}", new, source)
      source = re.sub(rf"\b{re.escape(old[:-1])}\b(?!\.)", new[:-1], source)
    else:
      source = re.sub(rf"\b{re.escape(old)}\b", new, source)
  return source


def imports_sorted(source: str | None) -> str | None:
  """``source`` with each run of consecutive import statements in one order, merged where they
  import from the same module: the renamed imports of a move, re-sorted by the linter, do
  what the base's did. Comments go; docstrings stay (the code comparison drops them)."""
  if source is None:
    return None
  import ast
  tree = ast.parse(source)

  def key(node):
    return (type(node).__name__, getattr(node, "module", None) or "", getattr(node, "level", 0))

  for node in ast.walk(tree):
    for field in ("body", "orelse", "finalbody"):
      body = getattr(node, field, None)
      if not isinstance(body, list):
        continue
      out, run = [], []
      for stmt in [*body, None]:
        if isinstance(stmt, (ast.Import, ast.ImportFrom)):
          run.append(stmt)
          continue
        merged = {}
        for imp in run:
          k = key(imp) if isinstance(imp, ast.ImportFrom) else (key(imp), len(merged))
          if k in merged:
            merged[k].names = merged[k].names + imp.names
          else:
            merged[k] = imp
        for imp in merged.values():
          imp.names = sorted(imp.names, key=lambda a: (a.name, a.asname or ""))
        out += sorted(merged.values(), key=ast.dump)
        run = []
        if stmt is not None:
          out.append(stmt)
      setattr(node, field, out)
  return ast.unparse(tree)


def same_moved_code(base: str | None, today: str | None, path: str) -> bool:
  """Whether ``today``'s module holds ``base``'s code once the moves' imports are renamed (:func:`as_moved`)
  and import runs put in one order (:func:`imports_sorted`)."""
  from benchmarks.results_header import same_code
  return same_code(base, today, path) or same_code(imports_sorted(as_moved(base)), imports_sorted(today), path)


def use_todays_weights(tree: pathlib.Path) -> list[str]:
  """Put today's shipped weights (``nlosjax/weights/``) into ``tree``; returns the names that differed.

  The probe asks whether the *code* computes the same numbers. Weights are an input to it,
  like the probe's fixed data: a network shipped since the base (the replaced ``real-ours_s``)
  is a new result, judged by the files its own command regenerates, and both trees run it.
  """
  import shutil
  src, dst = provenance.ROOT / "nlosjax" / "weights", tree / "nlosjax" / "weights"
  changed = sorted(p.name for p in src.iterdir() if p.is_dir() and any(
      not (dst / p.name / f.name).exists() or (dst / p.name / f.name).read_bytes() != f.read_bytes()
      for f in p.iterdir()))
  shutil.rmtree(dst, ignore_errors=True)
  shutil.copytree(src, dst)
  return changed


def run_probe(tree: pathlib.Path, out: pathlib.Path, *, log=print, probe: pathlib.Path = PROBE) -> dict:
  """Run today's ``probe`` script on ``tree``'s packages; returns its arrays (and its JSON under ``"_meta"``)."""
  env = {**os.environ, "PYTHONPATH": str(tree)}
  script = out.with_name(f"{out.stem}_probe.py")          # run from a folder of its own: no
  script.write_text(probe.read_text())                      # benchmarks/ module shadows anything
  for sibling in HERE.glob("equivalence_probe*.py"):        # today's probes, importable by each other
    (out.parent / sibling.name).write_text(sibling.read_text())
  t0 = time.perf_counter()
  got = subprocess.run([sys.executable, str(script), str(out)], cwd=tree, env=env, capture_output=True,
                       text=True)
  if got.returncode:
    raise RuntimeError(f"the probe failed on {tree}:\n{got.stderr[-3000:]}")
  log(f"probe on {tree}: {time.perf_counter() - t0:.0f} s")
  meta = json.loads(out.with_suffix(".json").read_text())
  for package in ("nlosjax", "experiments"):                  # the tree's code, not another's
    if pathlib.Path(meta[package]).resolve() != (tree / package).resolve():
      raise RuntimeError(f"the probe on {tree} imported {package} from {meta[package]}")
  with np.load(out) as f:
    arrays = {k: f[k] for k in f.files}
  return {**arrays, "_meta": meta}


def compare(old: dict, new: dict, tolerance: float = TOLERANCE) -> list[dict]:
  """One row per probe group (``data/lct``, ``train/ours``, ...): arrays, identical, worst relative change.

  An array only ``new`` holds (a metric added since) is listed as added and fails nothing: the
  numbers measured before are unchanged. An array only ``old`` holds fails its probe.
  """
  keys = sorted((set(old) | set(new)) - {"_meta"})
  groups: dict[str, dict] = {}
  for k in keys:
    g = "/".join(k.split("/")[:2])
    row = groups.setdefault(g, {"probe": g, "arrays": 0, "identical": 0, "worst": 0.0, "missing": [],
                                "added": []})
    if k not in old:
      row["added"].append(k)
      continue
    row["arrays"] += 1
    if k not in new:
      row["missing"].append(k)
      continue
    a, b = np.asarray(old[k]), np.asarray(new[k])
    if a.shape != b.shape:
      row["missing"].append(f"{k} (shape {a.shape} -> {b.shape})")
      continue
    if a.dtype == b.dtype and a.tobytes() == b.tobytes():
      row["identical"] += 1
      continue
    a64, b64 = a.astype(np.float64), b.astype(np.float64)
    same_nan = np.array_equal(np.isnan(a64), np.isnan(b64))
    scale = np.nanmax(np.abs(a64)) if np.isfinite(a64).any() else 1.0
    diff = np.nanmax(np.abs(a64 - b64)) / max(scale, 1e-30) if same_nan else np.inf
    row["worst"] = max(row["worst"], float(diff))
  for row in groups.values():
    row["passed"] = not row["missing"] and row["worst"] <= tolerance
  return list(groups.values())


def changed_modules(base: str) -> list[str]:
  """Project modules whose code (not comments or docstrings) differs between ``base`` and the working tree."""
  from benchmarks.results_header import GitFiles as _GitFiles
  from benchmarks.results_header import same_code as _same_code
  files = provenance.project_files()
  listed = subprocess.run(["git", "ls-tree", "-r", "--name-only", base], cwd=provenance.ROOT,
                          capture_output=True, text=True, check=True).stdout.split()
  old = {p for p in listed if p.endswith(".py") and p.split("/")[0] in provenance.PACKAGES}
  show = _GitFiles()
  try:
    return sorted(p for p in files | old
                  if not _same_code(show(base, p) if p in old else None,
                                    (provenance.ROOT / p).read_text() if p in files else None, p))
  finally:
    show.close()


def write(out: pathlib.Path, base: str, rows: list[dict], changed: list[str], seconds: dict,
          command: str, weights: tuple[str, ...] = (), probe: pathlib.Path = PROBE) -> dict:
  modules = provenance.code_modules(["benchmarks.equivalence", f"benchmarks.{probe.stem}"])
  # Nothing compared is nothing shown: a base without the probed code (the measured protocol
  # before it existed) writes no array, and its record carries nothing.
  compared = sum(r["arrays"] for r in rows)
  passed = all(r["passed"] for r in rows) and compared > 0
  record = {"base": base, "head": provenance.git_commit(), "tolerance": TOLERANCE, "passed": passed,
            "changed": changed, "closure": modules, "probes": rows, "seconds": seconds,
            "weights_since_base": list(weights)}
  lines = [f"# Results carried forward: the code at {base[:12]} and today's, side by side", "",
           *provenance.provenance(command, modules), "",
           f"Every probe of `benchmarks/{probe.name}` run on commit `{base[:12]}`'s tree and on "
           f"this one (probe times: base {seconds['base']:.0f} s, today {seconds['today']:.0f} s). "
           f"A probe passes when every array is within {TOLERANCE:g} of the base value, relative to "
           "the base array's largest magnitude (float32 rounding); `identical` counts arrays equal "
           "bit for bit. Both trees run today's shipped weights (`use_todays_weights`; shipped since the"
           " base: " + (", ".join(f"`{w}`" for w in weights) or "none") + "): the check is of the code.", "",
           "| probe | arrays | identical | largest relative change | passed | added since |",
           "|---|---|---|---|---|---|"]
  for r in rows:
    worst = "0" if r["worst"] == 0 else f"{r['worst']:.2e}"
    mark = "yes" if r["passed"] else ("no (" + "; ".join(r["missing"][:2]) + ")" if r["missing"] else "no")
    added = ", ".join(f"`{a.split('/', 2)[-1]}`" for a in r["added"][:4]) + \
        (f" and {len(r['added']) - 4} more" if len(r["added"]) > 4 else "")
    lines.append(f"| {r['probe']} | {r['arrays']} | {r['identical']} | {worst} | {mark} | {added} |")
  verdict = ("every probe passed" if passed else "a probe moved beyond rounding"
             if compared else "nothing was compared")
  lines += ["", f"**Verdict: {verdict}.** "
            + ("A results file current at the base commit, whose changed modules all lie in this "
               "command's import closure (or in the union with the other records against this base), "
               "is carried forward by `python -m benchmarks.index`."
               if passed else "Nothing is carried forward from this base."), "",
            f"Modules whose code changed since `{base[:12]}` ({len(changed)}):", ""]
  inside = set(modules)
  lines += [f"- `{m}`" + ("" if m in inside else " (outside this check's closure)") for m in changed]
  out.write_text("\n".join(lines) + "\n")
  out.with_suffix(".json").write_text(json.dumps(record, indent=1) + "\n")
  return record


def records(results: pathlib.Path) -> list[str]:
  """The names of the check's records in ``results``: ``equivalence`` and any ``equivalence_<base>``.

  Several records let a file current at another commit be carried too: ``python -m
  benchmarks.equivalence --base A B`` writes ``equivalence.md`` (against A) and
  ``equivalence_B.md``.
  """
  return sorted(p.stem for p in results.glob(f"{NAME}*.json")
                if (p.stem == NAME or p.stem.startswith(f"{NAME}_")) and p.with_suffix(".md").exists())


def carried_forward(entry, *, results: pathlib.Path, files=None) -> str | None:
  """``"carried forward from <base> by <record>.md"`` where the rule above holds for ``entry``
  with the :func:`records` against one base, else None.

  The records against one base (the main probe's and the measured probe's) together cover the
  union of their closures, each of them current and passed: a file whose changed modules lie
  partly in one probe's closure and partly in the other's is carried by both, named together.
  A base against which any record failed carries nothing: a closure is static (the measured
  probe's holds the training code it imports but never runs), so one probe's pass must not
  stand in for another's failure.

  ``entry``: a :class:`benchmarks.results_header.Entry` that is stale today.
  """
  if entry.name in records(results) or not entry.digest:
    return None
  files = provenance.project_files() if files is None else files
  by_base: dict[str, dict[str, set[str]]] = {}     # base -> {record: its closure}
  failed: set[str] = set()
  for name in records(results):
    record = json.loads((results / f"{name}.json").read_text())
    if not record.get("passed"):
      failed.add(record["base"])           # a probe moved against this base: it carries nothing
      continue
    closure = _current_closure(results, name, files)
    if closure is not None:
      by_base.setdefault(record["base"], {})[name] = closure
  for base, closures in by_base.items():
    if base in failed:
      continue
    origin, needed = base[:7], _changed_since(entry, base, files)
    if needed is None:                     # not current at the base: carried there, then on?
      origin, needed = _carried_at(entry, base, results, files) or (None, None)
      if needed is None:
        continue                           # neither: nothing to carry
      origin = f"{origin} via {base[:7]}"
    for name, closure in closures.items():  # one record alone, where one does
      if needed <= closure:
        return f"carried forward from {origin} by {name}.md"
    if needed <= set().union(*closures.values()):
      used = [n for n in closures if needed & closures[n]]
      return f"carried forward from {origin} by " + " + ".join(f"{n}.md" for n in used)
  return None


#: The index file whose committed rows :func:`_carried_at` reads at a base.
INDEX_PATH = "benchmarks/README.md"


def state_at(base: str, name: str, show) -> str | None:
  """The state column ``base``'s committed index (:data:`INDEX_PATH`) gave results file ``name``,
  or None where that commit has no index or no row for it. ``show(commit, path)``: a file's text."""
  text = show(base, INDEX_PATH)
  row = re.compile(rf"\| \[{re.escape(name)}\.md\]\([^)]*/{re.escape(name)}\.md\) \|")  # wherever it lay
  for line in (text or "").splitlines():
    if row.match(line):
      cells = [c.strip() for c in re.split(r"(?<!\\)\|", line)[1:-1]]
      return cells[6] if len(cells) == 9 else None   # file, what, command, date, machine, commit, state
  return None


def _carried_at(entry, base: str, results: pathlib.Path, files) -> tuple[str, set[str]] | None:
  """``(origin, changed)`` where ``entry`` was carried forward at ``base`` (its committed index,
  checked at that commit by ``tests/test_benchmarks_index.py``, says so, from ``origin``) and its
  results file is byte for byte the one ``base`` holds; ``changed``: today's paths of its modules
  whose code differs between ``base`` and today. None otherwise.

  The chain is sound link by link: the records ``base``'s index named showed that the changes
  from ``origin`` to ``base`` move no probe; the records against ``base`` show the same of the
  changes since. So each stop needs records against the last landed commit only, not against
  every commit a results file was current at.
  """
  from benchmarks.results_header import GitFiles as _GitFiles
  own = entry.path or results / f"{entry.name}.md"
  show = _GitFiles()
  try:
    # where the file lies today, else where every results file lay before studies kept their own
    at_base = next((text for where in (_repo_path(own), f"benchmarks/results/{entry.name}.md")
                    if where and (text := show(base, where)) is not None), None)
    if at_base is None or not own.exists() or own.read_text() != at_base:
      return None
    said = state_at(base, entry.name, show) or ""
    found = re.match(r"carried forward from (\w+)", said)
    if not found:
      return None                          # current at the base is the direct rule's case
    return found.group(1), _changed_code(entry, base, show, files)
  finally:
    show.close()


def _repo_path(path: pathlib.Path) -> str | None:
  """``path`` relative to the repository root, as git names it; None for a path outside it."""
  path = pathlib.Path(path).resolve()
  return path.relative_to(provenance.ROOT).as_posix() if path.is_relative_to(provenance.ROOT) else None


def _current_closure(results: pathlib.Path, name: str, files) -> set[str] | None:
  """The modules ``name``'s header lists (its probe's closure) where that header is current
  today, else None."""
  from benchmarks.results_header import read_entry
  own = read_entry(results / f"{name}.md")
  if any(m not in files for m in own.modules) or provenance.code_digest(own.modules) != own.digest:
    return None
  return set(own.modules)


def _changed_since(entry, base: str, files) -> set[str] | None:
  """Today's paths of ``entry``'s modules whose code changed since ``base`` (moves and renames
  aside), or None where ``entry`` was not current at ``base``."""
  from benchmarks.results_header import GitFiles as _GitFiles
  show = _GitFiles()
  try:
    if any(show(base, m) is None for m in entry.modules):
      return None
    if provenance.code_digest(entry.modules, lambda p: show(base, p)) != entry.digest:
      return None
    return _changed_code(entry, base, show, files)
  finally:
    show.close()


def today_text(path: str) -> str:
  """The working tree's text of ``path`` (a project file): what every base is compared with."""
  return (provenance.ROOT / path).read_text()


def _changed_code(entry, base: str, show, files) -> set[str]:
  """Today's paths of ``entry``'s modules whose code differs between ``base`` and today (moves
  and renames aside). A module is read at ``base`` under the path the entry names, or, where
  ``base`` has it already moved, under today's; one that ``base`` lacks counts as changed."""
  changed = set()
  for m in entry.modules:
    today = moved_path(m)
    then = show(base, m)
    if then is None:
      then = show(base, today)
    now = today_text(today) if today in files else None
    if then is None or not same_moved_code(then, now, m):
      changed.add(today)
  return changed


def record_name(base: str, first: bool, probe: str = "main") -> str:
  """A record's results file name: ``equivalence.md`` for the first base named, ``equivalence_<base>.md`` after;
  ``equivalence_<probe>.md`` and ``equivalence_<probe>_<base>.md`` for a probe other than ``main``."""
  stem = NAME if probe == "main" else f"{NAME}_{probe}"
  return f"{stem}.md" if first else f"{stem}_{base}.md"


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--base", required=True, nargs="+",
                 help="the commit(s) the results files were current at; today's probe runs once for all")
  p.add_argument("--out", nargs="+", default=None,
                 help="one results file per base (default: equivalence.md for the first, "
                      "equivalence_<BASE>.md for the others)")
  p.add_argument("--probe", choices=tuple(PROBES), default="main",
                 help="which probe script runs (PROBES); each writes records of its own")
  args = p.parse_args(argv)
  probe = PROBES[args.probe]
  outs = args.out or [str(HERE / "results" / record_name(b, i == 0, args.probe))
                      for i, b in enumerate(args.base)]
  if len(outs) != len(args.base):
    p.error(f"--out names {len(outs)} files for {len(args.base)} bases")
  command = f"python -m benchmarks.equivalence --base {' '.join(args.base)}" + \
      (f" --out {' '.join(args.out)}" if args.out else "") + \
      (f" --probe {args.probe}" if args.probe != "main" else "")
  passed = True
  with tempfile.TemporaryDirectory() as d:
    t0 = time.perf_counter()
    new = run_probe(provenance.ROOT, pathlib.Path(d) / "today.npz", probe=probe)
    today = time.perf_counter() - t0
    for name, out in zip(args.base, outs):
      base = subprocess.run(["git", "rev-parse", name], cwd=provenance.ROOT, capture_output=True,
                            text=True, check=True).stdout.strip()
      tree = pathlib.Path(d) / f"base-{base[:12]}"
      subprocess.run(["git", "worktree", "add", "--detach", str(tree), base], cwd=provenance.ROOT,
                     check=True, capture_output=True)
      try:
        weights = use_todays_weights(tree)
        t0 = time.perf_counter()
        old = run_probe(tree, pathlib.Path(d) / f"base-{base[:12]}.npz", probe=probe)
        seconds = {"base": time.perf_counter() - t0, "today": today}
      finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=provenance.ROOT,
                       capture_output=True)
      rows = compare(old, new)
      record = write(pathlib.Path(out), base, rows, changed_modules(base), seconds, command, weights, probe)
      for r in rows:
        print(f"  {r['probe']}: {r['identical']}/{r['arrays']} identical, worst {r['worst']:.2e}"
              f"{'' if r['passed'] else '  FAILED'}")
      print(f"wrote {out}: {'passed' if record['passed'] else 'FAILED'}")
      passed = passed and record["passed"]
  return 0 if passed else 1


if __name__ == "__main__":
  sys.exit(main())
