"""The README's quick start is what CI runs, its lock-file line matches the lock, and the README
and ``docs/`` quote results files with their commits."""

import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parents[1]


def quick_start_commands() -> list[str]:
  """The bash blocks of the README's "Quick start" section, in order."""
  readme = (ROOT / "README.md").read_text()
  section = readme.split("## Quick start", 1)[1].split("\n## ", 1)[0]
  return [block.strip() for block in re.findall(r"```bash\n(.*?)```", section, re.S)]


def test_quick_start_has_the_two_commands():
  commands = quick_start_commands()
  assert commands[:2] == ['pip install -e . && python -m experiments.train',
                          'pip install -e ".[test]" && python -m pytest -q']


def test_ci_runs_the_readme_test_command_in_a_fresh_environment():
  ci = [line.strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()
        if line.strip() and not line.lstrip().startswith("#")]
  install, test = quick_start_commands()[1].split(" && ")
  assert any(l.startswith("python3 -m venv") for l in ci)
  venv = next(i for i, l in enumerate(ci) if l.startswith("python3 -m venv"))
  assert ci.index(install) > venv and ci.index(test) > ci.index(install)
  # The main job too (under CI), in the same environment, after the tests: its install, then
  # .ci/main_job, which runs its command under a hang guard.
  install_job, job = quick_start_commands()[0].split(" && ")
  assert ci.index("bash .ci/main_job") > ci.index(install_job) > ci.index(test)
  # Each in a phase of its own, timed in the table CI ends with (tests/test_ci.py runs it).
  phases = {l.split('"')[1]: i for i, l in enumerate(ci) if l.startswith('phase "')}
  assert list(phases) == ["venv + install", "lint", "suite", "suite (full tier)", "main-job install",
                          "main job"]
  assert phases["venv + install"] < ci.index(install) < phases["lint"] < ci.index("ruff check .")
  assert phases["lint"] < phases["suite"] < ci.index(test) < phases["suite (full tier)"]
  assert phases["suite (full tier)"] < ci.index(f"{test} --tier full") < phases["main-job install"]
  assert phases["main-job install"] < ci.index(install_job) < phases["main job"] < ci.index("bash .ci/main_job")
  assert any(l.startswith("timeout ") and l.endswith(job)
             for l in (ROOT / ".ci" / "main_job").read_text().splitlines())



def test_lock_file_is_generated_and_installable_as_the_readme_says():
  readme = (ROOT / "README.md").read_text()
  lock = (ROOT / "requirements-lock.txt").read_text()
  assert 'pip install -r requirements-lock.txt -e ".[test]"' in readme
  assert "Written whole by: bash .ci/lock" in lock
  pins = [l for l in lock.splitlines() if l and not l.startswith("#")]
  assert pins and all(re.fullmatch(r"[A-Za-z0-9._-]+==[A-Za-z0-9.+!_-]+", p) for p in pins), pins
  names = {p.split("==")[0].lower().replace("_", "-") for p in pins}
  for needed in ("jax", "jaxlib", "flax", "optax", "orbax-checkpoint", "numpy", "pytest"):
    assert needed in names, needed


PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
#: Headings a newcomer looks for, each within the README's first 100 lines.
FRONT_HEADINGS = ("## Reconstruct my capture", "## Try the shipped network", "## Train on a GPU",
                  "## Use the kernels in my code")


def test_the_readme_is_short_and_answers_the_first_questions_early():
  lines = (ROOT / "README.md").read_text().splitlines()
  assert len(lines) <= 200, len(lines)
  for heading in FRONT_HEADINGS:
    assert heading in lines, heading
    assert lines.index(heading) < 100, (heading, lines.index(heading) + 1)
  assert lines.index("## Quick start") < min(lines.index(h) for h in FRONT_HEADINGS)


def test_the_readme_links_every_docs_page():
  readme = (ROOT / "README.md").read_text()
  for page in sorted((ROOT / "docs").glob("*.md")):
    assert f"(docs/{page.name})" in readme, page.name


def _prose(page: pathlib.Path) -> str:
  """A page's text outside its code blocks."""
  return "".join(page.read_text().split("```")[::2])


def _quoting_units(text: str):
  """A page's paragraphs (blank-line separated), list items and table rows, each as one string."""
  for block in re.split(r"\n\s*\n", text):
    rows = [l for l in block.splitlines() if l.lstrip().startswith("|")]
    rest = "\n".join(l for l in block.splitlines() if not l.lstrip().startswith("|"))
    yield from rows
    yield from (item for item in re.split(r"\n(?=\s*(?:[-*]|\d+\.) )", rest) if item.strip())


NUMBER = re.compile(r"\d\.\d|\d+ ?(?:s|ms|min|dB|x|%)\b")
RESULTS_FILE = re.compile(r"results/([A-Za-z0-9_]+)\.(?:md|json|png)")


def test_the_readme_and_docs_quote_each_results_file_with_its_commit():
  """A paragraph, list item or table row of the README or docs/ that quotes a number and names a
  results file names the commit that file was written at (its header's, first 7 digits): a file
  regenerated at another commit makes the quote say which numbers it now quotes."""
  from benchmarks import index
  commits = {e.name: e.commit.split()[0][:7] for e in index.entries()}
  bad = []
  for page in PAGES:
    for unit in _quoting_units(_prose(page)):
      named = sorted(n for n in set(RESULTS_FILE.findall(unit)) if n in commits)
      missing = [f"{n} ({commits[n]})" for n in named if commits[n] not in unit]
      if missing and NUMBER.search(unit):
        bad.append(f"{page.name}: {', '.join(missing)}: {unit.strip()[:100]}...")
  assert not bad, "README or docs/ quote results files without their commit:\n" + "\n".join(bad)


def test_every_finding_names_its_results_file():
  """Each section of docs/results.md and each finding of the README's results that quotes a
  number names a results file, one that exists."""
  from benchmarks.index import results_folders
  results = {p.name for folder in results_folders() for p in folder.iterdir()}
  readme = (ROOT / "README.md").read_text().split("## Results at a glance", 1)[1].split("\n## ", 1)[0]
  findings = [f for f in re.split(r"\n(?=- )", readme) if f.startswith("- ")]
  sections = re.split(r"\n(?=## )", _prose(ROOT / "docs" / "results.md"))[1:]   # after the intro
  assert len(findings) == 5 and len(sections) > 5
  bad = []
  for unit in findings + sections:
    if NUMBER.search(unit):
      named = re.findall(r"results/([A-Za-z0-9_]+\.(?:md|json|png))", unit)
      if not named or not all(n in results for n in named):
        bad.append(unit.strip()[:100])
  assert not bad, "findings without their results file:\n" + "\n".join(bad)


def test_what_users_read_speaks_of_the_software_not_of_how_it_was_made():
  pages = PAGES + [ROOT / "benchmarks" / "README.md", ROOT / "nlosjax" / "weights" / "README.md",
                   ROOT / "CHANGELOG.md"]
  bad = [f"{p.relative_to(ROOT)}: {m.group(0)}" for p in pages
         for m in re.finditer(r"(?i)\bissues? #?\d+|/tmp/|\bsessions?\b|\btracker\b", p.read_text())]
  assert not bad, bad
