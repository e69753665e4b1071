"""Every Python block of the README and of ``docs/*.md`` runs as written: an example that breaks fails CI.

Each block runs in a fresh interpreter from a temporary folder, with the repository on
``PYTHONPATH`` as after ``pip install -e .``; blocks must not need files a fresh clone
lacks, and write only into the folder they run from. A block that needs an optional extra says
so on its first line (``# needs: mitsuba (pip install -e ".[render]")``) and is skipped where
that module is not installed.
"""

import importlib.util
import pathlib
import re
import subprocess
import sys

import pytest

from tests.xla_options import record_user_environment, user_environment

ROOT = pathlib.Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def python_blocks(page: pathlib.Path) -> list[str]:
  """The ```python blocks of one Markdown page, in order."""
  return re.findall(r"```python\n(.*?)```", page.read_text(), re.S)


BLOCKS = [(page.relative_to(ROOT).as_posix(), i, block)
          for page in PAGES for i, block in enumerate(python_blocks(page))]


def test_the_pages_have_python_blocks():
  assert (ROOT / "docs").is_dir() and len(PAGES) > 1
  names = {name for name, _, _ in BLOCKS}
  for page in ("README.md", "docs/api.md", "docs/reconstruct.md", "docs/dataset.md"):
    assert page in names, page


def test_the_readme_has_the_composition_examples():
  # The composition examples live in the README and docs/api.md: together they show each piece.
  text = "\n".join(block for name, _, block in BLOCKS if name in ("README.md", "docs/api.md"))
  for needed in ("selective_scan", "bidirectional_scan", "exp_floor", "MambaMixer", "STMambaBlock",
                 "CrossSTMambaBlock", "phasor_field_loss", "value_and_grad", "load_pretrained"):
    assert needed in text, needed


@pytest.mark.parametrize("name, index, block", BLOCKS, ids=[f"{n}:{i}" for n, i, _ in BLOCKS])
@pytest.mark.full
def test_python_block_runs(name, index, block, tmp_path):
  needs = re.match(r"# needs: ([A-Za-z_][\w.]*)", block)
  if needs and importlib.util.find_spec(needs.group(1)) is None:
    pytest.skip(f"{name} Python block {index} needs {needs.group(1)}, not installed")
  env = {**user_environment(), "PYTHONPATH": str(ROOT), "JAX_PLATFORMS": "cpu"}
  res = subprocess.run([sys.executable, "-c", block], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=600)
  assert res.returncode == 0, f"{name} Python block {index}:\n{block}\n{res.stderr[-3000:]}"


def test_blocks_run_without_the_suites_xla_settings():
  """The settings the suite adds are removed and the user's own restored (absent stays absent)."""
  env = {"XLA_FLAGS": "--a=1", "OTHER": "x"}
  record_user_environment(env)
  env.update({"JAX_DISABLE_MOST_OPTIMIZATIONS": "1", "XLA_FLAGS": "--a=1 --xla_cpu_use_fusion_emitters=false"})
  assert user_environment(env) == {"XLA_FLAGS": "--a=1", "OTHER": "x"}
  assert user_environment({"OTHER": "x"}) == {"OTHER": "x"}
