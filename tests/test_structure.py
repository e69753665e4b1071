"""Imports run downward only: ``nlosjax`` <- ``experiments`` <- ``benchmarks``.

Every ``import`` and ``from ... import`` statement of every module, top level or inside
a function (or in a string run as a subprocess script), is read with ``ast``.

Inside ``nlosjax`` no two modules import each other, directly or round a longer circle
(a cycle such as ``physics.depth_range`` and ``physics.reconstruct`` importing each other inside
functions hides an order dependence).
"""

import ast
import importlib
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


# ------------------------------------------------------------- cycles inside nlosjax
def _nlosjax_modules() -> dict[str, pathlib.Path]:
  """Dotted module name -> file, for every module and package of ``nlosjax``."""
  modules = {}
  for path in sorted((ROOT / "nlosjax").rglob("*.py")):
    parts = path.relative_to(ROOT).with_suffix("").parts
    modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
  return modules


def _import_graph() -> dict[str, set[str]]:
  """Module -> the ``nlosjax`` modules it imports (top level or inside functions).

  ``from pkg import name`` is an edge to ``pkg.name`` when that is a module (importing a
  submodule runs its package's ``__init__`` first, which Python does for every import and
  is no circle), else to ``pkg`` (the name comes from its ``__init__``).
  """
  modules = _nlosjax_modules()
  graph = {}
  for name, path in modules.items():
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    edges = set()
    for node in ast.walk(ast.parse(path.read_text())):
      if isinstance(node, ast.Import):
        for alias in node.names:
          parts = alias.name.split(".")
          edges |= {".".join(parts[:i]) for i in range(len(parts), 0, -1)
                    if ".".join(parts[:i]) in modules}
      elif isinstance(node, ast.ImportFrom):
        if node.level:
          base = package.split(".")[:len(package.split(".")) - node.level + 1]
          source = ".".join(base + ([node.module] if node.module else []))
        else:
          source = node.module
        subs = {f"{source}.{a.name}" for a in node.names} & set(modules)
        edges |= subs
        if len(subs) < len(node.names) and source in modules:
          edges.add(source)
    graph[name] = edges - {name}
  return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
  """The strongly connected components of more than one module (Tarjan), sorted."""
  index, low, stack, on_stack, found = {}, {}, [], set(), []

  def visit(v):
    index[v] = low[v] = len(index)
    stack.append(v)
    on_stack.add(v)
    for w in sorted(graph[v]):
      if w not in index:
        visit(w)
        low[v] = min(low[v], low[w])
      elif w in on_stack:
        low[v] = min(low[v], index[w])
    if low[v] == index[v]:
      component = []
      while not component or component[-1] != v:
        component.append(stack.pop())
        on_stack.discard(component[-1])
      if len(component) > 1:
        found.append(sorted(component))

  for v in sorted(graph):
    if v not in index:
      visit(v)
  return sorted(found)


def test_the_cycle_finder_sees_imports_inside_functions_and_relative_ones():
  graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": {"f"}, "f": {"e"}}
  assert _cycles(graph) == [["a", "b", "c"], ["e", "f"]]
  assert _cycles({"a": {"b"}, "b": set()}) == []
  edges = _import_graph()
  assert "nlosjax.physics.methods.lct" in edges["nlosjax.physics.methods.fbp"]
  assert "nlosjax.physics._validate" in edges["nlosjax.physics.methods.fbp"]      # from pkg import mod
  assert "nlosjax.physics" not in edges["nlosjax.physics.methods.fbp"]
  assert "nlosjax.physics.setup" in edges["nlosjax.physics"]                    # the __init__


def test_depth_range_and_reconstruct_import_one_way():
  """The dispatch imports the depth-range estimator, which uses f-k from its own module."""
  edges = _import_graph()
  assert "nlosjax.physics.depth_range" in edges["nlosjax.physics.reconstruct"]
  assert "nlosjax.physics.reconstruct" not in edges["nlosjax.physics.depth_range"]
  assert "nlosjax.physics.methods.fk" in edges["nlosjax.physics.depth_range"]
  # Every public name is still where it was. (``nlosjax.physics.reconstruct`` the attribute is
  # the function, which the package re-exports over the module's name: hence import_module.)
  from nlosjax.physics import auto_depth_range, estimate_depth_range, fk, reconstruct
  rec = importlib.import_module("nlosjax.physics.reconstruct")
  dr = importlib.import_module("nlosjax.physics.depth_range")
  fk_module = importlib.import_module("nlosjax.physics.methods.fk")
  assert rec.fk is fk is fk_module.fk and rec.reconstruct is reconstruct
  assert rec.auto_depth_range is auto_depth_range
  assert dr.estimate_depth_range is estimate_depth_range and dr.auto_depth_range is auto_depth_range


def test_no_import_cycle_among_nlosjax_modules():
  cycles = _cycles(_import_graph())
  assert not cycles, "modules that import each other (directly or round a circle):\n" + "\n".join(
      " <-> ".join(c) for c in cycles)


# ------------------------------------------------------------- variant names in one place
#: Files that may spell a variant's name: the registry alone.
SPELLED_AT = ("nlosjax/variants.py",)


def _spelled_variant_names(path: pathlib.Path, names) -> list[int]:
  """Lines of ``path`` whose code (docstrings aside, f-strings included) holds a variant name as a string."""
  tree = ast.parse(path.read_text())
  docstrings = set()
  for node in ast.walk(tree):
    if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
      docstrings |= {id(s.value) for s in node.body if isinstance(s, ast.Expr) and isinstance(s.value, ast.Constant)}
  return sorted({n.lineno for n in ast.walk(tree) if isinstance(n, ast.Constant) and n.value in names
                 and isinstance(n.value, str) and id(n) not in docstrings})


def test_variant_names_are_spelled_only_in_the_registry(tmp_path):
  from nlosjax.variants import IK, LFE, OURS, OURS_S, USM, VARIANTS
  names = set(VARIANTS)
  assert names == {OURS, OURS_S, USM, LFE, IK}
  allowed = {p for pattern in SPELLED_AT for p in ROOT.glob(pattern)}
  assert allowed == {ROOT / "nlosjax/variants.py"}
  bad = [f"{path.relative_to(ROOT)}:{line}" for package in ("nlosjax", "experiments", "benchmarks")
         for path in sorted((ROOT / package).rglob("*.py")) if path not in allowed
         for line in _spelled_variant_names(path, names)]
  assert not bad, "variant names spelled outside nlosjax.variants (import OURS, USM, ... from it):\n" + "\n".join(bad)
  # The finder sees a name in code and in an f-string, and not in a docstring or a longer name.
  sample = tmp_path / "sample.py"
  sample.write_text('"""Trains "ours"."""\n\ndef f(x):\n  """Reads ``"usm"``."""\n  return x["ours_s"]\n\n'
                    'y = f"{d[\'lfe\']}"\nz = "ours_f5"\n')
  assert _spelled_variant_names(sample, names) == [5, 7]
