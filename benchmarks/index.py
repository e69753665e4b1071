"""Write ``benchmarks/README.md``, the index of ``benchmarks/results/``, from the results files.

    python -m benchmarks.index            # rewrite benchmarks/README.md
    python -m benchmarks.index --check    # exit 1 if it differs from what the files say

Each row is read from one results file's header: its title, the command that
wrote it ("Produced by `...`"), its date, machine and commit, and the newest
"Still holds at <hash>" banner. Nothing here is typed by hand but the goal
each benchmark is judged against (``GOALS``), so the index cannot drift from
the files it points to; ``tests/test_benchmarks_index.py`` checks that the committed
index is this module's output. Numbers live in the results files themselves.
"""

from __future__ import annotations

import argparse
import dataclasses
import pathlib
import re
import sys

HERE = pathlib.Path(__file__).resolve().parent
RESULTS = HERE / "results"
INDEX = HERE / "README.md"

# What each results file is judged against (from the issue that asked for it); a file not
# named here shows "none stated".
GOALS = {
    "data": "near-linear speed-up with `--workers` (issue 22)",
    "dry_run": "refuses a run above 90 % of device memory",
    "main_job": "the main job within 1200 s (20 min on 2 cores)",
    "physics": "each method <= 1.3x its FFT floor and >= 1x the same-variant NumPy/SciPy twin, "
               "at 64² and 128² (issue 20)",
    "real": "the network ahead of every classic method against every other method's full scan "
            "(issue 18)",
    "scan": "associative <= 4x / <= 10x the exp floor (forward / fwd+bwd), best <= 2x / <= 6x, "
            "auto within 10 % of the best, fwd+bwd peak <= 3x inputs + outputs (issue 21)",
    "scan_torch": "associative >= 5x faster than mambapy's pscan, fwd+bwd (issue 21)",
    "table1": "Ours - Ours-S >= +0.5 dB; Ours >= best classic + 3 dB (issue 18); "
              "Ours >= USM + 0.5 dB (issue 19)",
    "table1_independent": "Ours >= best classic + 1 dB, recall >= 0.85 (issue 18)",
    "table1_low_photon": "Ours - Ours-S >= +0.5 dB where photons are scarce (issue 18)",
    "table2_controls": "full - no-SSM >= +1 dB (issue 18)",
    "table2_controls_low_photon": "full - no-SSM >= +1 dB where photons are scarce (issue 18)",
    "tradeoff": "halving the depth range cuts LCT and network time by >= 1.6x",
}

HEADER = """# Benchmarks: an index

Each benchmark measures its candidates and what they are judged against (FFT floors, exp floors,
NumPy/SciPy twins, the full model) side by side in one run and prints ratios, since absolute
times on a shared machine move between runs. Each results file in `results/` is written whole
by the command named in its first lines ("Produced by `...`"), with the date, machine and
commit; a `Still holds at <hash>` banner is a later check that the code it measures did not
change what it reports, not a rerun. The numbers are in the files.
`pip install -e ".[bench]"` installs PyTorch and mambapy, needed only for
`benchmarks/scan_torch.py`. Imports run downward only: `nlosjax` <- `experiments` <-
`benchmarks` (provenance and the NumPy twins live in `experiments/`).

This file is written by `python -m benchmarks.index` from the results files' headers; rerun it
after any benchmark (a test fails while it is out of date).
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
  still_holds: str    # newest "Still holds at <hash>" banner, or ""


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
  # Banners are quoted lines at the top, newest first: "> **Still holds at <hash>** (...)".
  return Entry(path.stem, _first(r"^# (.+)$", body), command, date, machine, commit,
               _first(r"^> \*\*Still holds at ([0-9a-f]{7,40})\*\*", text, ""))


def entries(results: pathlib.Path = RESULTS) -> list[Entry]:
  """Every ``*.md`` results file, sorted by name."""
  return [read_entry(p) for p in sorted(results.glob("*.md"))]


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
    owner = max((t for t in tables if rest == t or rest.startswith(t + "_")), key=len, default=None)
    if owner == stem:
      out.append(p.name)
  return out


def render(results: pathlib.Path = RESULTS) -> str:
  """The index's Markdown text."""
  lines = [HEADER, "| results file | what | command | date (UTC) | machine | commit | "
           "latest check | goal | companions |", "|---|---|---|---|---|---|---|---|---|"]
  found = entries(results)
  tables = {e.name for e in found}
  for e in found:
    cells = [f"[{e.name}.md](results/{e.name}.md)", e.title.replace("|", "\\|"),
             f"`{e.command}`".replace("|", "\\|"), e.date, e.machine, e.commit,
             f"still holds at {e.still_holds}" if e.still_holds else "",
             GOALS.get(e.name, "none stated"),
             ", ".join(companions(results, e.name, tables))]
    lines.append("| " + " | ".join(cells) + " |")
  return "\n".join(lines) + "\n"


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--check", action="store_true", help="exit 1 if benchmarks/README.md is stale")
  args = p.parse_args(argv)
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
