"""The README's quick start is what CI runs, and its lock-file line matches the lock."""

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
  assert ci.index(f"{install_job} && bash .ci/main_job") > ci.index(test)
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


def _quoting_units(text: str):
  """The README's paragraphs (blank-line separated) and table rows, each as one string."""
  for block in re.split(r"\n\s*\n", text):
    rows = [l for l in block.splitlines() if l.lstrip().startswith("|")]
    rest = "\n".join(l for l in block.splitlines() if not l.lstrip().startswith("|"))
    yield from rows
    if rest.strip():
      yield rest


def test_the_readme_quotes_only_current_results_files_or_says_the_number_is_stale():
  """A paragraph or table row that quotes a number from a stale results file says "stale"."""
  from benchmarks import index
  states = {e.name: index.state(e) for e in index.entries()}
  readme = (ROOT / "README.md").read_text().split("```")
  prose = "".join(readme[::2])                    # outside code blocks
  bad = []
  for unit in _quoting_units(prose):
    named = set(re.findall(r"results/([A-Za-z0-9_]+)\.(?:md|json|png)", unit))
    numbers = re.search(r"\d\.\d|\d+ ?(?:s|ms|min|dB|x|%)\b", unit)
    stale = sorted(n for n in named if n in states and states[n] != "current")
    if stale and numbers and "stale" not in unit.lower():
      bad.append(f"{', '.join(stale)}: {unit.strip()[:100]}...")
  assert not bad, "README quotes stale results without saying so:\n" + "\n".join(bad)
