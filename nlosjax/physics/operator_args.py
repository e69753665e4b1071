"""The physics layer's operators as arguments of a jitted function, not constants baked into it.

:class:`~nlosjax.models.physics_layer.FeatureTransform` reads its LCT operators (PSF
spectrum, resampling matrices) from :func:`~nlosjax.physics.operators.lct_operators`.
Read inside ``jax.jit`` they are concrete arrays, so XLA receives them as
constants: at the paper preset's physics layer the PSF spectrum alone is a
256 x 129 x 512 complex64 array (135 MB) written into every program's HLO
(272 MB of text), hashed for the compilation cache, stored in its entries and
constant-folded where XLA sees fit. Measured on 2 EPYC cores: the paper-scale
physics layer compiles in 3.5 s with them as constants and in 0.2 s with them
as arguments.

Here the operators become an argument instead:

* :func:`operators_of` traces a module's ``init`` on shapes only (nothing is
  computed) and records the operators every physics layer of it reads, as an
  :class:`OperatorTable` (a pytree: the keys are static, the arrays are leaves);
* :func:`bind` jits a function with the table as one more argument and binds the
  table to it: ``bound(*args) == fn(*args)``, ``bound.lower(*args).compile()(*args)``
  too; inside the trace :func:`lookup` hands each layer the traced argument for
  its key.

Outside :func:`bind` (op by op, or a user's own ``jax.jit``) the layers read the
cached constants as before; the numbers are the same either way.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
from typing import Any, Callable, Hashable

import jax
import numpy as np

__all__ = ["OperatorTable", "lookup", "operators_of", "traced_with_operators", "bind", "replicate"]


@jax.tree_util.register_pytree_node_class
@dataclasses.dataclass(frozen=True)
class OperatorTable:
  """Operators keyed by what built them: ``keys`` (static, hashable) and ``values`` (pytrees of arrays)."""

  keys: tuple[Hashable, ...] = ()
  values: tuple[Any, ...] = ()

  def get(self, key):
    for k, v in zip(self.keys, self.values):
      if k == key:
        return v
    return None

  def tree_flatten(self):
    return self.values, self.keys

  @classmethod
  def tree_unflatten(cls, keys, values):
    return cls(tuple(keys), tuple(values))


class _Recorder(dict):
  """Key -> operators met while tracing under :func:`operators_of`."""


_ACTIVE: contextvars.ContextVar = contextvars.ContextVar("nlosjax_operator_table", default=None)


@contextlib.contextmanager
def _active(table):
  token = _ACTIVE.set(table)
  try:
    yield table
  finally:
    _ACTIVE.reset(token)


def lookup(key: Hashable, build: Callable[[], Any]):
  """The operators for ``key``: the bound argument inside :func:`bind`, else ``build()`` (cached constants).

  Args:
    key: hashable description of the operators (equal keys, equal operators).
    build: returns them as concrete arrays (called outside any trace's reach).
  """
  table = _ACTIVE.get()
  if isinstance(table, _Recorder):
    if key not in table:
      table[key] = build()
    return table[key]
  if isinstance(table, OperatorTable):
    found = table.get(key)
    if found is not None:
      return found
  return build()


def operators_of(fn: Callable, *example_args) -> OperatorTable:
  """Every operator ``fn(*example_args)`` reads through :func:`lookup`, traced on shapes only.

  ``example_args`` may be ``jax.ShapeDtypeStruct``; nothing but the operators
  themselves is computed. E.g. ``operators_of(model.init, key, x_shape)``.
  """
  return traced_with_operators(fn, *example_args)[1]


def traced_with_operators(fn: Callable, *example_args) -> tuple[Any, OperatorTable]:
  """``(jax.eval_shape(fn, *example_args), operators_of(fn, *example_args))`` from one trace.

  E.g. a module's parameter shapes and its physics operators from one trace of its
  ``init`` (a trace of a large network's ``init`` takes about as long as compiling a
  small program).
  """
  recorder = _Recorder()
  with _active(recorder):
    shapes = jax.eval_shape(fn, *example_args)
  return shapes, OperatorTable(tuple(recorder), tuple(recorder.values()))


def replicate(table: OperatorTable, sharding) -> OperatorTable:
  """``table`` laid out as ``sharding`` (e.g. replicated over a mesh); works across processes."""
  def put(a):
    host = np.asarray(a)
    return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])
  return jax.tree.map(put, table)


class _BoundCompiled:
  def __init__(self, compiled, table):
    self._compiled, self._table = compiled, table

  def __call__(self, *args):
    return self._compiled(*args, self._table)

  def __getattr__(self, name):                 # memory_analysis, cost_analysis, as_text, ...
    return getattr(self._compiled, name)


class _BoundLowered:
  def __init__(self, lowered, table):
    self._lowered, self._table = lowered, table

  def compile(self, *args, **kwargs):
    return _BoundCompiled(self._lowered.compile(*args, **kwargs), self._table)

  def __getattr__(self, name):
    return getattr(self._lowered, name)


class Bound:
  """``fn`` jitted with an :class:`OperatorTable` as its last argument, the table bound.

  ``bound(*args)``, ``bound.lower(*args)`` (whose ``compile()`` result is called
  with ``*args`` too); ``bound.jitted`` is the jitted ``fn(*args, table)``,
  ``bound.table`` the table.
  """

  def __init__(self, fn: Callable, table: OperatorTable, **jit_kwargs):
    def with_table(*args):
      *args, tab = args
      with _active(tab):
        return fn(*args)
    self.table = table
    self.jitted = jax.jit(with_table, **jit_kwargs)
    self.__wrapped__ = fn

  def __call__(self, *args):
    return self.jitted(*args, self.table)

  def lower(self, *args):
    return _BoundLowered(self.jitted.lower(*args, self.table), self.table)


def bind(fn: Callable, table: OperatorTable, **jit_kwargs) -> Bound:
  """``jax.jit(fn)`` with ``table``'s operators entering as an argument; see :class:`Bound`.

  ``jit_kwargs`` go to ``jax.jit`` (``donate_argnums`` count ``fn``'s own
  arguments; ``in_shardings``, if given, must include one for the table, last).
  """
  return Bound(fn, table, **jit_kwargs)
