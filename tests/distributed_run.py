"""Driver of tests/test_distributed.py, run in subprocesses (not a test module).

    python -m tests.distributed_run devices DATA OUT         # one process, 4 CPU devices
    python -m tests.distributed_run worker DATA OUT PORT ID  # one of 2 processes, 2 devices each

``devices``: the tiny config trained on meshes of 4, 2 and 1 devices, and
checkpoints written on one mesh size restored and continued on another;
writes ``OUT/devices.json`` (differences) and ``OUT/straight4.npz``.
``worker``: joins a 2-process ``jax.distributed`` run (4 devices in all), trains the
same config in a shared workdir and writes ``OUT/worker<ID>.npz`` and
``OUT/worker<ID>.json`` (what its loader read).
"""

import json
import os
import pathlib
import shutil
import sys


def _flat(params) -> dict:
  import jax
  import numpy as np
  return {jax.tree_util.keystr(p): np.asarray(x)
          for p, x in jax.tree_util.tree_flatten_with_path(params)[0]}


def _max_diff(a: dict, b: dict) -> float:
  import numpy as np
  assert a.keys() == b.keys()
  return max(float(np.max(np.abs(a[k] - b[k]))) for k in a)


def _setup(data):
  from nlosjax.data.dataset import open_dataset
  with open_dataset(data) as ds:
    return ds.setup


def devices(data, out):
  import jax

  from nlosjax import train as T
  from tests.tiny_run import tiny_config
  quiet = lambda s: None                                            # noqa: E731
  assert jax.device_count() == 4, jax.device_count()

  def run(n, steps, workdir):
    cfg = tiny_config(data, steps=steps, devices=n, batch_size=4)
    return T.train_model(T.RunConfig.from_dict(cfg), data, workdir, "ours_s", log=quiet)

  # Straight runs keep their checkpoints of steps 2 and 4 (tiny_config saves every 2 steps).
  straight = {n: _flat(T.to_host(run(n, 4, out / f"straight{n}")[1].params)) for n in (4, 2, 1)}
  result = {"straight_4_vs_1": _max_diff(straight[4], straight[1]),
            "straight_4_vs_2": _max_diff(straight[4], straight[2])}

  def restore_step2(workdir, n):
    """The step-2 checkpoint of ``workdir`` restored into a fresh state replicated on ``n`` devices."""
    cfg = tiny_config(data, steps=4, devices=n, batch_size=4)
    typed = T.RunConfig.from_dict(cfg)
    mcfg = T.model_config_for(typed, _setup(data), "ours_s")
    optim, weights = T.training_recipe(typed, "ours_s")
    batch = int(cfg["train"]["batch_size"])
    fresh = T.create_train_state(T.network(mcfg), mcfg.input_shape(batch),
                                 T.make_optimizer(optim, 4), jax.random.key(123), T.mesh_for(typed))
    ckpt = T.Checkpointer(workdir / "ours_s" / "checkpoints",
                          T.run_signature(mcfg, fresh.params, optim, weights, batch, 0), every=2)
    state, position = ckpt.restore(fresh, 2)
    ckpt.close()
    return state, position

  for written, read in ((4, 1), (4, 2), (1, 4), (2, 4)):
    # The written run as if killed after step 2: its workdir without the step-4 checkpoint.
    workdir = out / f"w{written}r{read}"
    shutil.copytree(out / f"straight{written}", workdir)
    shutil.rmtree(workdir / "ours_s" / "checkpoints" / "4")
    saved, _ = restore_step2(workdir, written)
    restored, position = restore_step2(workdir, read)
    on = {d.id for d in jax.tree.leaves(restored.params)[0].sharding.device_set}
    _, continued = run(read, 4, workdir)                            # resumes from step 2
    result[f"{written}->{read}"] = {
        "restored_vs_saved": _max_diff(_flat(T.to_host(restored.params)),
                                       _flat(T.to_host(saved.params))),
        "restored_opt_vs_saved": _max_diff(_flat(T.to_host(restored.opt_state)),
                                           _flat(T.to_host(saved.opt_state))),
        "restored_on_devices": len(on), "position": position, "step": int(continued.step),
        "continued_vs_straight_read": _max_diff(_flat(T.to_host(continued.params)), straight[read]),
        "continued_vs_straight_written": _max_diff(_flat(T.to_host(continued.params)),
                                                   straight[written])}
  import numpy as np
  np.savez(out / "straight4.npz", **straight[4])
  (out / "devices.json").write_text(json.dumps(result, indent=1))


def worker(data, out, port, pid):
  from nlosjax import train as T
  T.initialize_distributed(f"localhost:{port}", 2, pid)
  import jax
  import numpy as np

  from tests.tiny_run import tiny_config
  cfg = tiny_config(data, steps=4, batch_size=4)
  loader = T.make_loader(T.RunConfig.from_dict(cfg), data, "train", batch_size=4, shuffle=True, seed=0,
                         shard=(jax.process_index(), jax.process_count()))
  rows = loader.batch(0)
  _, state = T.train_model(T.RunConfig.from_dict(cfg), data, out / "shared", "ours_s", log=lambda s: None)
  np.savez(out / f"worker{pid}.npz", **_flat(T.to_host(state.params)))
  (out / f"worker{pid}.json").write_text(json.dumps({
      "process_count": jax.process_count(), "devices": jax.device_count(),
      "local_devices": jax.local_device_count(), "step": int(state.step),
      "rows": int(rows["measurement"].shape[0]),
      "examples": [[int(s), int(f)] for s, f in zip(rows["sequence"], rows["frame"])],
      "log_lines": len((out / "shared" / "ours_s" / "metrics.jsonl").read_text().splitlines())
      if pid == 0 else None}))


if __name__ == "__main__":
  sys.path.insert(0, os.getcwd())
  mode, data, out = sys.argv[1], sys.argv[2], pathlib.Path(sys.argv[3])
  if mode == "devices":
    devices(data, out)
  else:
    worker(data, out, int(sys.argv[4]), int(sys.argv[5]))
