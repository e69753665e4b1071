"""Config loading shared by the experiment entry points.

``--config`` names a preset (``cpu``, ``paper``) or a Python file defining
``get_config() -> dict``; ``--config.section.key=value`` overrides one entry
(the value is a Python literal, e.g. ``--config.train.steps=100``,
``--config.data.efficiency="(0.01, 0.3)"``, or a bare string).
"""

from __future__ import annotations

import ast
import importlib.util
import pathlib

from experiments import configs


def load_config(spec: str) -> dict:
  """A preset by name, or ``get_config()`` of a ``.py`` file."""
  path = pathlib.Path(spec)
  if spec.endswith(".py"):
    if not path.is_file():
      raise SystemExit(f"--config: no such file {spec}")
    module_spec = importlib.util.spec_from_file_location(f"_config_{path.stem}", path)
    module = importlib.util.module_from_spec(module_spec)
    module_spec.loader.exec_module(module)
    return module.get_config()
  try:
    return configs.get_config(spec)
  except ValueError as e:
    raise SystemExit(f"--config: {e}") from None


def apply_overrides(config: dict, overrides: list[str]) -> dict:
  """Apply ``--config.a.b=value`` arguments to the nested dict ``config`` (in place)."""
  for arg in overrides:
    if not arg.startswith("--config.") or "=" not in arg:
      raise SystemExit(f"unrecognised argument {arg!r}; overrides look like --config.train.steps=100")
    key, value = arg[len("--config."):].split("=", 1)
    *parents, leaf = key.split(".")
    node = config
    for p in parents:
      if not isinstance(node.get(p), dict):
        raise SystemExit(f"--config.{key}: no section {p!r} (sections: {sorted(node)})")
      node = node[p]
    if leaf not in node and parents and parents[0] not in ("model", "train"):
      raise SystemExit(f"--config.{key}: unknown key {leaf!r} (known: {sorted(node)})")
    try:
      node[leaf] = ast.literal_eval(value)
    except (ValueError, SyntaxError):
      node[leaf] = value
  return config
