"""A model config as a field-by-field JSON record, and the one rule that says whether a record matches.

A record is ``{"type": class name, field: value, ...}`` with nested dataclasses
(the :class:`~nlosjax.physics.Setup`) as records and tuples as lists. Checkpoints
and shipped weights written before records recorded the config's ``repr``; such a
string is read as a record by :func:`parse_repr` (a parser of literals, nothing is
evaluated), so old and new files are checked by :func:`compare` alike.

The rule: a recorded config matches a config when their types agree, every
recorded field holds the config's value, and every field the record lacks is at
its dataclass default (a field added to the class after the file was written;
its default keeps the behaviour the file was trained with).
"""

from __future__ import annotations

import ast
import dataclasses
from typing import Any

TYPE_KEY = "type"


def model_record(cfg) -> dict:
  """``cfg`` (a dataclass) as a JSON-ready record: ``{"type": name, field: value, ...}``."""
  if not dataclasses.is_dataclass(cfg) or isinstance(cfg, type):
    raise TypeError(f"model_record needs a dataclass instance, got {type(cfg).__name__}")
  return {TYPE_KEY: type(cfg).__name__, **{f.name: _value(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)}}


def _value(v):
  if dataclasses.is_dataclass(v) and not isinstance(v, type):
    return model_record(v)
  if isinstance(v, (tuple, list)):
    return [_value(x) for x in v]
  if isinstance(v, dict):
    return {str(k): _value(x) for k, x in v.items()}
  if v is None or isinstance(v, (bool, int, float, str)):
    return v
  raise TypeError(f"a model config field holds a {type(v).__name__} ({v!r}), which a record cannot hold")


def parse_repr(text: str) -> dict:
  """The record of a dataclass ``repr`` such as ``ModelConfig(setup=Setup(...), stride=4, ...)``.

  Only calls with keyword arguments and literals are read (``ast``; nothing is
  evaluated). Raises ``ValueError`` for anything else.
  """
  try:
    node = ast.parse(text, mode="eval").body
  except SyntaxError as e:
    raise ValueError(f"not a dataclass repr: {text[:80]!r} ({e.msg})") from None
  out = _node(node, text)
  if not isinstance(out, dict):
    raise ValueError(f"not a dataclass repr: {text[:80]!r}")
  return out


def _node(node, text: str):
  if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and not node.args:
    return {TYPE_KEY: node.func.id, **{k.arg: _node(k.value, text) for k in node.keywords}}
  if isinstance(node, (ast.Tuple, ast.List)):
    return [_node(x, text) for x in node.elts]
  try:
    return _value(ast.literal_eval(node))
  except (ValueError, TypeError, SyntaxError):
    raise ValueError(f"not a dataclass repr of literals: {ast.get_source_segment(text, node)!r} in "
                     f"{text[:80]!r}") from None


def as_record(recorded) -> dict:
  """A recorded model config as a record: a record is returned as is, a ``repr`` string parsed."""
  if isinstance(recorded, dict):
    return recorded
  if isinstance(recorded, str):
    return parse_repr(recorded)
  raise ValueError(f"a recorded model config is a record or a repr string, got {type(recorded).__name__}")


def compare(recorded, cfg) -> tuple[list[str], list[str]]:
  """``(differing, added)`` between a recorded config (record or ``repr``) and ``cfg``.

  ``differing``: ``"field: recorded value != value"`` for each field that breaks
  the rule of the module docstring (the type, a value, a recorded field ``cfg``
  lacks, a missing field off its default); nested configs are compared by the same
  rule. ``added``: the fields the record lacks that are at their defaults. The
  record matches when ``differing`` is empty.
  """
  rec = as_record(recorded)
  differing: list[str] = []
  added: list[str] = []
  _compare(rec, cfg, "", differing, added)
  return differing, added


def _compare(rec: dict, cfg, prefix: str, differing: list, added: list) -> None:
  name = type(cfg).__name__
  if rec.get(TYPE_KEY) != name:
    differing.append(f"{prefix or 'type'}: {rec.get(TYPE_KEY)!r} recorded, {name!r} now")
    return
  fields = {f.name: f for f in dataclasses.fields(cfg)}
  for key in sorted(set(rec) - set(fields) - {TYPE_KEY}):
    differing.append(f"{prefix}{key}: recorded ({rec[key]!r}) but not a field of {name}")
  for key, f in fields.items():
    value = getattr(cfg, key)
    if key not in rec:
      default = _default(f)
      if default is not dataclasses.MISSING and _value(value) == _value(default):
        added.append(prefix + key)
      else:
        differing.append(f"{prefix}{key}: not recorded, {value!r} now (its default: "
                         f"{'none' if default is dataclasses.MISSING else repr(default)})")
    elif dataclasses.is_dataclass(value) and isinstance(rec[key], dict):
      _compare(rec[key], value, f"{prefix}{key}.", differing, added)
    elif _same(rec[key], _value(value)):
      continue
    else:
      differing.append(f"{prefix}{key}: {rec[key]!r} recorded, {_value(value)!r} now")


def _default(f: dataclasses.Field) -> Any:
  if f.default is not dataclasses.MISSING:
    return f.default
  if f.default_factory is not dataclasses.MISSING:
    return f.default_factory()
  return dataclasses.MISSING


def _same(a, b) -> bool:
  """Equal as JSON values (a float recorded as ``2`` equals ``2.0``; a bool is not an int)."""
  if isinstance(a, bool) or isinstance(b, bool):
    return type(a) is type(b) and a == b
  if isinstance(a, list) and isinstance(b, list):
    return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
  if isinstance(a, dict) and isinstance(b, dict):
    return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
  return a == b


def matches(recorded, cfg) -> bool:
  """Whether a recorded config (record or ``repr``) matches ``cfg`` (:func:`compare`)."""
  return not compare(recorded, cfg)[0]
