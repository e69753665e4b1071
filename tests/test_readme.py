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

