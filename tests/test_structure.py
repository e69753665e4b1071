"""Imports run downward only: ``nlosjax`` <- ``experiments`` <- ``benchmarks`` (issue 23).

Every ``import`` and ``from ... import`` statement of every module, top level or inside
a function (or in a string run as a subprocess script), is read with ``ast``.
"""

import ast
import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
#: package -> packages it must not import
FORBIDDEN = {"nlosjax": ("experiments", "benchmarks", "tests"), "experiments": ("benchmarks", "tests")}


def _imported(path: pathlib.Path) -> set[str]:
  tree = ast.parse(path.read_text())
  names = set()
  for node in ast.walk(tree):
    if isinstance(node, ast.Import):
      names |= {a.name.split(".")[0] for a in node.names}
    elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
      names.add(node.module.split(".")[0])
    elif isinstance(node, ast.Constant) and isinstance(node.value, str):
      names |= set(re.findall(r"^\s*(?:from|import)\s+(\w+)", node.value, re.M))
  return names


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_imports_run_downward(package):
  bad = []
  for path in sorted((ROOT / package).rglob("*.py")):
    wrong = _imported(path) & set(FORBIDDEN[package])
    if wrong:
      bad.append(f"{path.relative_to(ROOT)} imports {sorted(wrong)}")
  assert not bad, "\n".join(bad)
