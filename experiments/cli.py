"""``--config`` for every entry point: a preset file read by ``ml_collections.config_flags``.

``--config`` names a preset (``cpu``, ``paper``, ``real``: ``experiments/configs/NAME.py``) or
a Python file whose ``get_config()`` returns a ``ConfigDict``; ``--config.section.key=value``
overrides one entry, in config_flags' own syntax (``--config.train.steps=100``,
``'--config.data.photons=(5.0, 200.0)'``, ``'--config.train.variants=("ours",)'``). The config
is locked, so an unknown key, a value of the wrong type or a missing file exits with one line
before any work. The other flags (``--workdir``, ``--resume-from``, ...) stay argparse's: the
config flags are parsed on a private ``absl.flags.FlagValues``.
"""

from __future__ import annotations

import argparse
import contextlib
import pathlib
import warnings

from experiments import configs

#: The ``--help`` epilog of the entry points that take overrides.
OVERRIDES_HELP = """\
config overrides (ml_collections.config_flags):
  --config.SECTION.KEY=VALUE   override one entry of the config, e.g. --config.train.steps=100
                               --config.data.renderer=lct '--config.data.photons=(50.0, 2000.0)'
                               '--config.train.variants=("ours",)'; sections: data (data.scene,
                               data.loader, data.num_sequences, data.physics), model, train (train.optim,
                               train.loss, train.stop), usm, lfe, ik (each .model, .optim), independent.
                               An unknown key or a value of the wrong type exits naming it.
"""


def config_file(spec: str) -> pathlib.Path:
  """The file ``--config spec`` names: a preset's module, or the ``.py`` file itself (``FILE:ARG`` passes ARG)."""
  if spec in configs.PRESETS:
    return configs.FOLDER / f"{spec}.py"
  path = pathlib.Path(spec.split(":", 1)[0])
  if path.suffix != ".py":
    raise SystemExit(f"--config {spec}: neither a preset ({', '.join(configs.PRESETS)}) nor a .py file")
  if not path.is_file():
    raise SystemExit(f"--config {spec}: no such file")
  return path


def load_config(spec: str = configs.DEFAULT, overrides=()) -> dict:
  """The config ``--config spec`` names with the ``--config.KEY=VALUE`` ``overrides`` applied, as a plain dict.

  Read by ``config_flags.DEFINE_config_file(lock_config=True)``; the dict is
  :func:`experiments.configs.to_dict` of the ConfigDict (unset keys left out), or the dict a
  file's ``get_config()`` returns as it is.
  Raises ``SystemExit`` with one line for a missing file, an unknown key or a bad value.
  """
  from absl import flags
  from ml_collections import ConfigDict, config_flags

  path = config_file(spec)
  argument = spec.partition(":")[2]                # FILE.py:ARG -> get_config("ARG")
  source = f"{path}:{argument}" if argument else str(path)
  argv = ["", f"--config={source}", *overrides]
  flag_values = flags.FlagValues()
  config_flags.DEFINE_config_file("config", None, lock_config=True, flag_values=flag_values, sys_argv=argv)
  try:
    with _quiet():
      rest = flag_values(argv)
      config = flag_values.config
  except Exception as e:  # config_flags: KeyError/AttributeError (unknown key), flags.Error (bad value), ...
    raise SystemExit(_one_line(e, spec, source, overrides)) from None
  if rest[1:]:
    raise SystemExit(f"unrecognised argument(s) {' '.join(rest[1:])}; overrides look like --config.train.steps=100")
  return configs.to_dict(config) if isinstance(config, ConfigDict) else config     # a file may return a dict


def _one_line(error: Exception, spec: str, source: str, overrides) -> str:
  """One line for a config that did not load: the override whose key the config lacks, else the error's last line."""
  import difflib

  from ml_collections import ConfigDict
  from ml_collections.config_flags import config_flags
  if isinstance(error, (KeyError, AttributeError)):
    with _quiet():
      config = config_flags.ConfigFileFlagParser("config").parse(source)
    for arg in overrides:
      node, where = config, "config"
      for key in override_key(arg):
        if not isinstance(node, (ConfigDict, dict)):
          return f"{arg.split('=', 1)[0]}: {where} is a value ({node!r}), not a section"
        if key not in node:
          close = difflib.get_close_matches(key, list(node), n=1)
          hint = f" (did you mean {close[0]!r}?)" if close else ""
          return f"{arg.split('=', 1)[0]}: {where} has no key {key!r}{hint}; it has: {', '.join(sorted(node))}"
        node, where = node[key], f"{where}.{key}"
  lines = [line.strip() for line in str(error).splitlines() if line.strip()]
  return f"--config {spec}: {lines[-1] if lines else type(error).__name__}"


@contextlib.contextmanager
def _quiet():
  """config_flags loads a config file with the deprecated ``load_module()``: no warning for that."""
  with warnings.catch_warnings():
    warnings.filterwarnings("ignore", "the load_module", DeprecationWarning)
    yield


def override_key(arg: str) -> tuple[str, ...]:
  """``"--config.a.b=v" -> ("a", "b")``: the key an override sets."""
  return tuple(arg.split("=", 1)[0].lstrip("-").split(".")[1:])


def config_parser(description: str, **kwargs) -> argparse.ArgumentParser:
  """An ``ArgumentParser`` with the ``--config`` option and the overrides epilog (:data:`OVERRIDES_HELP`)."""
  parser = argparse.ArgumentParser(description=description, epilog=OVERRIDES_HELP,
                                   formatter_class=argparse.RawDescriptionHelpFormatter, **kwargs)
  parser.add_argument("--config", default=configs.DEFAULT,
                      help=f"preset name ({', '.join(configs.PRESETS)}) or a .py file whose get_config()"
                           " returns a ConfigDict (default: %(default)s)")
  return parser


def parse_config(parser: argparse.ArgumentParser, argv=None) -> tuple[argparse.Namespace, dict, list[str]]:
  """``(args, config, overrides)``: the parsed flags, the ``--config`` config with the overrides applied, and those.

  Every argument the parser does not know goes to config_flags (:func:`load_config`).
  """
  args, overrides = parser.parse_known_args(argv)
  return args, load_config(args.config, overrides), overrides
