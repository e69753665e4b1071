"""Config loading shared by the experiment entry points (``experiments.train``, ``experiments.make_dataset``, ...).

``--config`` names a preset (``cpu``, ``paper``, ``real``) or a Python file
defining ``get_config() -> dict``; ``--config.section.key=value`` overrides one
entry (the value is a Python literal, e.g. ``--config.train.steps=100``,
``--config.data.efficiency="(0.01, 0.3)"``, or a bare string). An override of
a key that its section does not know (neither in the config nor read by the
code that consumes the section) exits before any work with the section's known
keys; a known sub-section the config lacks (e.g. ``usm.optim``) is created.
:func:`config_parser` and :func:`parse_config` give every entry point the same
``--config`` option, ``--help`` epilog and parsing.
"""

from __future__ import annotations

import argparse
import ast
import difflib
import importlib.util
import pathlib

from experiments import configs

#: The ``--help`` epilog of the entry points that take overrides.
OVERRIDES_HELP = """\
config overrides:
  --config.SECTION.KEY=VALUE   override one entry of the config (a Python literal or a bare string),
                               e.g. --config.train.steps=100 --config.data.renderer=lct
                               '--config.data.photons=(50.0, 2000.0)'; sections: data (data.scene,
                               data.loader, data.num_sequences, data.physics), model, train (train.optim,
                               train.loss, train.stop), usm (usm.model, usm.optim), independent.
                               An unknown key or section exits with the known ones.
"""


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


def config_parser(description: str, **kwargs) -> argparse.ArgumentParser:
  """An ``ArgumentParser`` with the ``--config`` option and the overrides epilog (:data:`OVERRIDES_HELP`)."""
  parser = argparse.ArgumentParser(description=description, epilog=OVERRIDES_HELP,
                                   formatter_class=argparse.RawDescriptionHelpFormatter, **kwargs)
  parser.add_argument("--config", default=configs.DEFAULT,
                      help=f"preset name ({', '.join(configs.PRESETS)}) or a .py file defining get_config()"
                           " (default: %(default)s)")
  return parser


def parse_config(parser: argparse.ArgumentParser, argv=None) -> tuple[argparse.Namespace, dict, list[str]]:
  """``(args, config, overrides)``: the parsed flags, the ``--config`` config with the overrides applied, and those.

  Every argument the parser does not know must be a ``--config.section.key=value``
  override (:func:`apply_overrides`); anything else, or an unknown key, exits.
  """
  args, overrides = parser.parse_known_args(argv)
  return args, apply_overrides(load_config(args.config), overrides), overrides


def override_key(arg: str) -> tuple[tuple[str, ...], str]:
  """``("--config.a.b=v") -> (("a", "b"), "v")``; exits on anything that is not an override."""
  if not arg.startswith("--config.") or "=" not in arg:
    raise SystemExit(f"unrecognised argument {arg!r}; overrides look like --config.train.steps=100")
  key, value = arg[len("--config."):].split("=", 1)
  return tuple(key.split(".")), value


def _schema(path: tuple[str, ...]) -> tuple[set[str], set[str]]:
  """``(keys, sub-sections)`` of section ``path``: the typed config's schema
  (:func:`nlosjax.train.config.section_schema`), plus the application's ``independent`` section.

  Imported lazily: only an override of a key missing from the config pays for it.
  """
  from nlosjax.train.config import section_schema
  if path == ():
    # "independent" (experiments.train) is replaced whole or edited where present: it needs a path.
    return {"independent"}, section_schema(path)[1]
  if path == ("independent",):
    return {"path", "sequences", "frames", "seed"}, set()        # experiments.train
  return section_schema(path)


def _unknown(name: str, what: str, missing: str, known) -> SystemExit:
  """The exit of override ``name``: ``what`` ``missing``, the closest known name, all of them."""
  close = difflib.get_close_matches(missing, known, n=1)
  hint = f" (did you mean {close[0]!r}?)" if close else ""
  return SystemExit(f"{name}: {what} {missing!r}{hint}; known: {', '.join(sorted(known))}")


def apply_overrides(config: dict, overrides: list[str]) -> dict:
  """Apply ``--config.a.b=value`` arguments to the nested dict ``config`` (in place).

  A key is known when the config has it or the code consuming its section
  reads it (:func:`_schema`); any other key or section raises ``SystemExit``
  naming the known ones, before the config is used.
  """
  for arg in overrides:
    (*parents, leaf), value = override_key(arg)
    name = arg.split("=", 1)[0]
    node, path = config, ()
    for p in parents:
      if node.get(p) is None:
        sections = {k for k, v in node.items() if isinstance(v, dict)} | _schema(path)[1]
        if p not in sections:
          where = f"section {'.'.join(path)} has no sub-section" if path else "no section"
          raise _unknown(name, where, p, sections)
        node[p] = {}                      # a known section the config leaves out (defaults apply)
      elif not isinstance(node[p], dict):
        raise SystemExit(f"{name}: {'.'.join(path + (p,))} is a value ({node[p]!r}), not a section")
      node, path = node[p], path + (p,)
    if leaf not in node:
      keys, sections = _schema(path)
      known = set(node) | keys | sections
      if leaf not in known:
        raise _unknown(name, f"section {'.'.join(path)} has no key" if path else "no section", leaf, known)
    try:
      node[leaf] = ast.literal_eval(value)
    except (ValueError, SyntaxError):
      node[leaf] = value
  return config
