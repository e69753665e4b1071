"""Data parallelism: meshes of devices, batches split over them, several processes (``jax.distributed``)."""

from __future__ import annotations

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P


def initialize_distributed(coordinator: str, num_processes: int, process_id: int) -> None:
  """Join a multi-process run (``jax.distributed.initialize``) before any device is used.

  On CPU the cross-process collectives use gloo (XLA:CPU has no default
  implementation), so the same command runs on a laptop, a CPU cluster or
  GPUs. Each process then sees every process's devices in ``jax.devices()``.
  """
  if num_processes < 1 or not 0 <= process_id < num_processes:
    raise ValueError(f"need 0 <= process_id < num_processes, got {process_id} of {num_processes}")
  if num_processes == 1:
    return
  try:
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
  except (AttributeError, ValueError):   # an older JAX without the option
    pass
  jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes,
                             process_id=process_id)


def make_mesh(devices=None) -> Mesh:
  """A 1D ``Mesh`` named ``"data"`` over ``devices`` (default: every device of every host)."""
  devices = np.asarray(devices if devices is not None else jax.devices())
  return Mesh(devices.reshape(-1), ("data",))


def mesh_for(config) -> Mesh:
  """The data-parallel mesh of a run (a :class:`~nlosjax.train.config.RunConfig`): every device,
  or the first ``train.devices``.

  With several processes (``jax.distributed``) the mesh spans every process's
  devices and ``train.devices`` must be None.
  """
  n = config.train.devices
  if n is None:
    return make_mesh()
  n = int(n)
  if jax.process_count() > 1:
    raise ValueError("train.devices selects devices of one process; leave it None with jax.distributed")
  if not 1 <= n <= jax.device_count():
    raise ValueError(f"train.devices = {n}, but this process has {jax.device_count()} device(s)")
  return make_mesh(jax.devices()[:n])


def to_host(tree):
  """Fully replicated (global) arrays as NumPy on this host; works with several processes too."""
  def one(x):
    if isinstance(x, jax.Array) and not x.is_fully_addressable:
      if not x.is_fully_replicated:
        raise ValueError("to_host needs fully replicated arrays across processes")
      return np.asarray(x.addressable_data(0))
    return np.asarray(x)
  return jax.tree.map(one, tree)


def shard_batch(batch: dict, mesh: Mesh) -> dict:
  """Place a host batch on the mesh, split along axis 0 (the batch must divide evenly).

  With several processes each passes its own rows (``TripletLoader(shard=...)``):
  the global batch is their concatenation in process order.
  """
  n = mesh.devices.size
  sharding = NamedSharding(mesh, P("data"))
  out = {}
  for k, v in batch.items():
    v = np.asarray(v)
    if jax.process_count() > 1:
      out[k] = jax.make_array_from_process_local_data(sharding, v)
      continue
    if v.shape[0] % n:
      raise ValueError(f"batch size {v.shape[0]} of {k!r} is not divisible by the {n} devices")
    out[k] = jax.device_put(v, sharding)
  return out
