"""Write ``benchmarks/README.md``, the index of every results file, from the results files.

    python -m benchmarks.index             # rewrite benchmarks/README.md, print each file's state
    python -m benchmarks.index --check     # exit 1 if it differs from what the files say

Results files live in ``benchmarks/results/`` (performance) and in each study's own
``experiments/studies/<study>/results/`` (:func:`benchmarks.results_header.results_folders`).
Each row is read from one results file's header: its title, the command that
wrote it ("Produced by `...`"), its date, machine and commit, and its code
digest (``- Code: `...```, written by ``experiments.provenance.code_line``: a
SHA-256 over the project modules the command may run, with their list). The
index recomputes that digest on today's tree and shows the file as **current**
(same code) or **stale** (with the first commit after the file's own that
changed one of those modules, and which ones). Nothing here is typed by hand
but the goal each benchmark is judged against (``GOALS``), so the index cannot
drift from the files it points to; ``tests/test_benchmarks_index.py`` checks
that the committed index is this module's output. Numbers live in the results
files themselves.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import re
import sys

from benchmarks.results_header import Entry, git_output, read_entry, results_folders
from benchmarks.results_header import GitFiles as _GitFiles
from benchmarks.results_header import same_code as _same_code
from experiments import provenance

HERE = pathlib.Path(__file__).resolve().parent
RESULTS = HERE / "results"
INDEX = HERE / "README.md"

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
    "main_job": "the main job within 1200 s (20 min on 2 cores)",
    "mechanisms": "full - no-SSM and full - Ours-S with intervals at both photon budgets, every run "
                  "trained to its validation plateau; the SSM probe of a trained Ours",
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
("Produced by `...`"), with the date, machine and commit, and a digest of the project modules
that command may run. The "state" column recomputes that digest on the tree this index was
written from: **current** means the code is the same, **stale since <commit>** names the first
later commit that changed one of those modules (and which ones). A stale file is regenerated with
its command; until then the README and `docs/` mark the numbers they quote from it as stale. The
command column gives the command as it is typed today, and the one that ran where a study or its
results have moved since. The numbers are in the files. Files a later study supersedes are kept,
unindexed, in `experiments/studies/archive/`, whose README names what replaces each.
`pip install -e ".[bench]"` installs PyTorch and mambapy, needed only for
`benchmarks/scan_torch.py`. Imports run downward only: `nlosjax` <- `experiments` (the application,
then its studies) <- `benchmarks` (provenance and the NumPy twins live in `experiments/`).

This file is written by `python -m benchmarks.index` from the results files' headers; rerun it
after any benchmark (a test fails while it is out of date).

**On a GPU** (`device.md`): from the repository root run
`PYTHONPATH=. python -m benchmarks.device --out DIR` under a time limit below 10 minutes (the
command keeps itself within its own `--budget-s 480`); no install step and no network are needed.
Six files come back in `DIR`: `environment.json`, `correctness.json`, `scan_kernels.json`,
`paper_scale.json`, `classic.json` and `device.log`, each part's JSON written as the part runs, so
a cut-off run still returns what it measured. Then `python -m benchmarks.device --collect DIR`
writes `results/device.md` whole (the device named); rerun `python -m benchmarks.index`.
`python -m benchmarks.device --tiny` rehearses the same code paths on CPU in the test suite, so
the command cannot break unnoticed between GPU runs. The procedure: `docs/gpu.md`.
"""


def state(entry: Entry, files=None) -> str:
  """``"current"``, ``"stale since <commit> (<modules>)"``, ``"stale: ..."``, or ``"no code digest"``.

  Current: the digest of ``entry.modules`` as they are on disk now equals the recorded one.
  Stale: otherwise; where git can tell, the first commit after the file's own whose code
  (not comments or docstrings) differs in one of those modules, and the modules whose code
  differs today from the file's commit; "uncommitted edits" where no commit changed them.
  """
  if not entry.digest:
    return "no code digest"
  files = provenance.project_files() if files is None else files
  missing = [m for m in entry.modules if m not in files]
  if not missing and provenance.code_digest(entry.modules) == entry.digest:
    return "current"
  commit = entry.commit.split()[0]
  log = git_output("log", "--reverse", "--format=@%h", "--name-only", f"{commit}..HEAD", "--", *entry.modules)
  if log is None:
    return "stale (git cannot say since when)"
  touched: list[tuple[str, list[str]]] = []       # (commit, the modules it touched), oldest first
  for line in log.split():
    if line.startswith("@"):
      touched.append((line[1:], []))
    elif touched:
      touched[-1][1].append(line)
  show = _GitFiles()
  try:
    first = next((c for c, paths in touched
                  if any(not _same_code(show(f"{c}^", m), show(c, m), m) for m in paths)), None)
    changed = [m for m in entry.modules if m in missing
               or not _same_code(show(commit, m), (provenance.ROOT / m).read_text(), m)]
  finally:
    show.close()
  what = ", ".join(changed[:3]) + (f" and {len(changed) - 3} more" if len(changed) > 3 else "")
  where = f"since {first}" if first else "since uncommitted edits"
  return f"stale {where} ({what})" if what else f"stale {where}"


def entries(results: pathlib.Path | None = None) -> list[Entry]:
  """Every ``*.md`` results file of ``results`` (default: every folder of
  :func:`~benchmarks.results_header.results_folders`), sorted by name.

  Raises:
    ValueError: two folders hold results files of the same name (the index and the
      equivalence check know a file by its name).
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
  out = []
  for p in sorted(results.iterdir()):
    if p.suffix == ".md" or not p.name.startswith(stem):
      continue
    rest = p.stem
    # the longest table name this file starts with owns it
    owner = _owner(rest, tables)
    if owner == stem:
      out.append(p.name)
  return out


def states(results: pathlib.Path | None = None) -> dict[str, str]:
  """Each results file's :func:`state`, by file stem; a stale one carried forward says so.

  Carried forward: :func:`benchmarks.equivalence.carried_forward` (a committed check showed
  that the code changes since the file was current move no probed number beyond rounding).
  """
  from benchmarks.equivalence import carried_forward
  files = provenance.project_files()
  out = {}
  for e in entries(results):
    st = state(e, files)
    if st.startswith("stale"):
      st = carried_forward(e, results=RESULTS if results is None else results, files=files) or st
    out[e.name] = st
  return out


def render(results: pathlib.Path | None = None, computed: dict[str, str] | None = None) -> str:
  """The index's Markdown text; ``computed``: :func:`states` where the caller has them already."""
  lines = [HEADER, "| results file | what | command | date (UTC) | machine | commit | "
           "state | goal | companions |", "|---|---|---|---|---|---|---|---|---|"]
  from benchmarks.equivalence import as_moved
  found = entries(results)
  tables = {e.name for e in found}
  computed = states(results) if computed is None else computed
  for e in found:
    today = _outputs_moved(as_moved(e.command), found)   # as typed today (a study or its results moved)
    command = f"`{today}`" + ("" if today == e.command else f" (ran as `{e.command}`)")
    link = pathlib.Path(os.path.relpath(e.path, HERE)).as_posix()
    cells = [f"[{e.name}.md]({link})", e.title.replace("|", "\\|"),
             command.replace("|", "\\|"), e.date, e.machine, e.commit,
             f"**{st}**" if (st := computed[e.name]) == "current" else st,
             GOALS.get(e.name, "none stated"),
             ", ".join(companions(e.path.parent, e.name, tables))]
    lines.append("| " + " | ".join(cells) + " |")
  return "\n".join(lines) + "\n"


def _outputs_moved(command: str, found: list[Entry]) -> str:
  """``command`` with each ``benchmarks/results/<file>`` it names that lives in a study's results
  folder today written with today's path."""
  where = {e.name: e.path.parent for e in found}

  def today(m: re.Match) -> str:
    stem = _owner(m.group(1), where)
    if stem is None or where[stem] == RESULTS:
      return m.group(0)
    return (where[stem] / m.group(1)).relative_to(provenance.ROOT).as_posix() + m.group(2)
  return re.sub(r"benchmarks/results/([A-Za-z0-9_]+)(\.\w+)", today, command)


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--check", action="store_true", help="exit 1 if benchmarks/README.md is out of date")
  args = p.parse_args(argv)
  computed = states()
  text = render(computed=computed)
  if args.check:
    if comparable(INDEX.read_text()) != comparable(text):
      print("benchmarks/README.md is out of date: run python -m benchmarks.index", file=sys.stderr)
      return 1
    return 0
  INDEX.write_text(text)
  print(f"wrote {INDEX}")
  for name, st in computed.items():
    print(f"  {name}: {st}")
  return 0


def comparable(index_text: str) -> str:
  """The index with each stale file's "since <commit> (...)" dropped.

  A commit that changes code a results file depends on cannot name its own hash in the
  index it commits: before it, the file reads "stale: uncommitted edits"; after, "stale
  since <that commit>". Both are stale, and the committed index is compared on that.
  """
  return re.sub(r"\| stale[^|]*\|", "| stale |", index_text)


if __name__ == "__main__":
  sys.exit(main())
