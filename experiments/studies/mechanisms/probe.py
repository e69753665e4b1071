"""Does a trained ST-Mamba use its SSMs? Bypass them at inference, read the gates (no retraining).

Each SSM of the network is a :class:`~nlosjax.models.stmamba.SelectiveSSM`
module inside a block's SSM chain (``st_mamba0/ssm/temporal0``,
``cross_prev1_0/ssm_ref/spatial1``, ...; :func:`ssm_paths`). :func:`probed_apply`
runs the trained model under :func:`flax.linen.intercept_methods`: an SSM
whose entry in a boolean mask is set returns its input instead of its output
(the identity the no-SSM control trains with), and every block's gate branch
``SiLU(z)`` (the second half of its ``in_proj`` / ``in_proj_ref`` output) is
averaged on the way. The mask is an array argument, so one compiled program
serves every choice of bypassed modules; with nothing bypassed the model
computes what it computes without the probe (the mask selects the SSM's own
output element by element), up to rounding in the last place: it is another
XLA program, fused differently, and ``jax.jit`` keeps whichever executable it
compiled first, whatever ``jax_disable_most_optimizations`` says now.

The learned mixing weights that are parameters, not activations
(:func:`mixing_weights`): the spreading stage's skip gain and, with
``skip_frames="weighted"``, the softmax weights of the input frames.
"""

from __future__ import annotations

import functools
import re

import flax.linen as nn
import jax
import jax.numpy as jnp

from nlosjax.models.stmamba import CrossSTMambaBlock, SelectiveSSM, STMambaBlock

__all__ = ["ssm_paths", "gate_paths", "probed_apply", "mixing_weights"]

_GATE_PROJECTIONS = ("in_proj", "in_proj_ref")


def _walk(tree, prefix=()):
  """``(path, subtree)`` of every dict in a nested parameter tree, depth first in key order."""
  if hasattr(tree, "unfreeze"):
    tree = tree.unfreeze()
  if isinstance(tree, dict):
    yield prefix, tree
    for k in sorted(tree):
      yield from _walk(tree[k], prefix + (k,))


def _network_order(path: str):
  """Sort key: the per-frame ST-Mamba blocks first, then the cross blocks; in a chain, the mixer order."""
  parts = path.split("/")
  index = re.search(r"(\d+)$", parts[-1])
  return (0 if parts[0].startswith("st_mamba") else 1, parts[:-1], int(index.group(1)) if index else 0, path)


def ssm_paths(params) -> tuple[str, ...]:
  """Slash-joined module paths of every SSM (a subtree holding ``A_log``), in network order.

  ``params``: the model's ``"params"`` tree (arrays or shapes). E.g.
  ``st_mamba0/ssm/temporal0``, ``st_mamba0/ssm/spatial1``, ``cross_next1_0/ssm_nb/temporal0``.
  """
  return tuple(sorted(("/".join(p) for p, t in _walk(params) if "A_log" in t), key=_network_order))


def gate_paths(params) -> tuple[str, ...]:
  """Paths of every ST-Mamba / cross block (a subtree with an ``in_proj`` or ``in_proj_ref``), sorted."""
  return tuple(sorted(("/".join(p) for p, t in _walk(params) if any(k in t for k in _GATE_PROJECTIONS)),
                      key=_network_order))


def _module_path(module: nn.Module) -> str:
  return "/".join(str(p) for p in module.path)


@functools.lru_cache(maxsize=8)
def probed_apply(mcfg, ssms: tuple[str, ...], blocks: tuple[str, ...]):
  """The model's forward pass with SSMs switchable to the identity and the gates averaged, jitted.

  Args:
    mcfg: the model config (:class:`~nlosjax.models.network.ModelConfig`).
    ssms: the SSM paths the mask indexes (:func:`ssm_paths` of the params).
    blocks: the block paths whose gates are averaged (:func:`gate_paths`).
  Returns:
    ``fn(params, frames [B, F, T, h, w], bypass [len(ssms)] bool) -> (outputs,
    gates)``: the model's output dict, and ``block -> [2]`` float32: the sum of
    ``SiLU(z)`` over every position, channel and example of the batch, and the
    number of values summed (so batches combine into one mean). Compiled with
    nlosjax's input checks, as the evaluation's forward pass is.
  """
  from nlosjax.physics.checks import checked
  model = mcfg.module()
  index = {p: i for i, p in enumerate(ssms)}

  def run(params, frames, bypass):
    gates = {}

    def interceptor(next_fun, args, kwargs, context):
      module = context.module
      if context.method_name != "__call__":
        return next_fun(*args, **kwargs)
      if isinstance(module, SelectiveSSM):
        y = next_fun(*args, **kwargs)
        i = index.get(_module_path(module))
        if i is None:
          raise ValueError(f"SSM {_module_path(module)} is not among the probed paths {ssms}")
        return jnp.where(bypass[i], args[0].astype(y.dtype), y)
      if (isinstance(module, nn.Dense) and module.name in _GATE_PROJECTIONS
          and isinstance(module.parent, (STMambaBlock, CrossSTMambaBlock))):
        y = next_fun(*args, **kwargs)
        block = _module_path(module.parent)
        if block in blocks:
          z = jnp.split(y, 2, axis=-1)[1].astype(jnp.float32)
          gates[block] = jnp.stack([jnp.sum(jax.nn.silu(z)), jnp.float32(z.size)])
        return y
      return next_fun(*args, **kwargs)

    with nn.intercept_methods(interceptor):
      out = model.apply({"params": params}, frames)
    return out, gates

  return checked(run, operators=mcfg.physics_operators())


def mixing_weights(params) -> dict:
  """Learned mixing weights that are parameters: ``{"skip_gain": float, "skip_frame_weights": [F]}``.

  ``skip_gain``: the spreading stage's gain on the interpolated measured
  frame; ``skip_frame_weights``: ``softmax(skip_frame_logits)`` over the input
  frames (present with ``skip_frames="weighted"`` and ``F > 1``).
  """
  out = {}
  spread = params.get("spread", {})
  if "skip_gain" in spread:
    out["skip_gain"] = float(spread["skip_gain"])
  if "skip_frame_logits" in params:
    out["skip_frame_weights"] = [float(w) for w in jax.nn.softmax(jnp.asarray(params["skip_frame_logits"]))]
  return out
