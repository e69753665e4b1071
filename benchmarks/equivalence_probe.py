"""The fixed probes of ``benchmarks.equivalence``, run as a script on whichever tree is first on ``sys.path``.

    PYTHONPATH=TREE python benchmarks/equivalence_probe.py OUT.npz

Run by :mod:`benchmarks.equivalence` once on an earlier commit's tree and once on
today's, it writes every number the project's results files are made of, at a tiny
size, to ``OUT.npz`` (one array per probe value) and ``OUT.json`` (which tree and
how long each probe took). It uses only interfaces that the commits it compares share
(the dataset writer, ``train_model``, the evaluation protocol, the shipped weights,
``physics.reconstruct``), and nothing from ``benchmarks``, so today's probe runs on
an older tree. Probes, each on fixed seeds:

* ``data/<renderer>``: every array of a 4-sequence 16 x 16 dataset of each renderer
  family the presets use (light-cone, transport, the physics mix);
* ``train/<variant>``: Ours-S, Ours and USM trained 3 steps on the light-cone data:
  every parameter and each step's loss;
* ``evaluate``: the main job's evaluation of those models and the classic methods
  (settings tuned on validation) on the test split: every per-frame score;
* ``pretrained/<name>``: every shipped network's output on a fixed input of its shape;
* ``physics/<method>``: each classic reconstruction of a fixed rendered scene;
* ``main_job``: ``python -m experiments.train`` itself (its ``main``) on the light-cone data
  with a config file of these sizes: every cell of the table it writes.
"""

from __future__ import annotations

import json
import pathlib
import sys
import tempfile
import time

import numpy as np

TINY_DATA = dict(grid=16, num_bins=64, bin_width=264e-12, frames=4, input_stride=4, input_offset=2,
                 num_sequences={"train": 2, "val": 1, "test": 1}, render_batch=4)
TINY_MODEL = dict(width=4, d_state=2, extract_time_stride=2, extract_blocks=1, st_depth=1, cross_depth=1,
                  spread_min_width=1, volume_features=1, refine_width=2, conv_impl="fold")
TINY_USM = dict(trn_width=2, trn_kernels=(3, 9), fusion_widths=(), extract_width=1,
                refine=((2, 3), (2, 3)), render_widths=(2, 2))
RENDERERS = {"lct": dict(renderer="lct", retroreflective=0.0, photons=(1e3, 1e4)),
             "transport": dict(renderer="transport"),
             # Every PhysicsMix option drawn often (real_v4's choices), ambient light on.
             "mix": dict(renderer="mix", retroreflective=0.0, ambient=(100.0, 2e4),
                         physics={"retroreflective": 0.8, "tail": 0.8, "tail_weight": (0.1, 0.5),
                                  "tail_decay": (1e-10, 1e-9), "dark_counts": (0.5, 50.0),
                                  "gain_sigma": (0.05, 0.4), "time_shift": 1, "gate": 0.5,
                                  "gate_time": (2.0e-9, 2.6e-9)})}


def _config(path, renderer: str) -> dict:
  from experiments import configs
  cfg = configs.get_config("cpu")
  cfg["data"].update(TINY_DATA, **RENDERERS[renderer], path=str(path))
  cfg["model"] = dict(TINY_MODEL)
  cfg["usm"] = {"recipe": "ours", "model": dict(TINY_USM)}
  cfg["train"] = {"steps": 3, "batch_size": 2, "log_every": 1, "checkpoint_every": 3, "eval_batch_size": 2}
  cfg.pop("independent", None)
  return cfg


def _arrays(path) -> dict[str, np.ndarray]:
  """Every array of an HDF5 file by its path (the probe's own reader, not the library's)."""
  import h5py
  out = {}
  with h5py.File(path, "r") as f:
    f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
  return out


def probe_data(tmp: pathlib.Path, out: dict) -> dict:
  from nlosjax import train
  paths = {}
  for renderer in RENDERERS:
    path = tmp / f"{renderer}.h5"
    cfg = _config(path, renderer)
    train.ensure_dataset(train.RunConfig.from_dict(cfg), path, log=lambda s: None)
    for name, a in _arrays(path).items():
      out[f"data/{renderer}/{name}"] = a
    paths[renderer] = (cfg, path)
  return paths


def probe_train_and_evaluate(cfg: dict, path, tmp: pathlib.Path, out: dict) -> None:
  import jax

  from nlosjax import train
  from nlosjax.evaluation import baselines, protocol
  cfg = train.RunConfig.from_dict(cfg)     # the one reader; the library takes it typed
  trained = {}
  for variant in ("ours_s", "ours", "usm"):
    mcfg, state = train.train_model(cfg, path, tmp / "run", variant, log=lambda s: None)
    params = train.to_host(state.params)
    for p, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
      out[f"train/{variant}/{jax.tree_util.keystr(p)}"] = np.asarray(leaf)
    rows = train.read_metrics(tmp / "run" / variant / "metrics.jsonl")
    out[f"train/{variant}/loss"] = np.array([r["loss"] for r in rows])
    trained[variant] = (mcfg, params)
  data = protocol.load_split(cfg, path, "val", batch_size=2)
  data["loader"].close()
  settings = baselines.tune(data["measurement"], data["intensity"], data["depth"], data["setup"],
                            data["stride"], batch_size=2, log=lambda s: None)
  ev = protocol.evaluate(cfg, path, trained, split="test", classic_settings=settings, log=lambda s: None)
  for method, scores in ev["scores"].items():
    for metric, v in scores.items():
      out[f"evaluate/{method}/{metric}"] = np.asarray(v, np.float64)


def probe_pretrained(out: dict) -> None:
  from nlosjax import inference
  for name, variant in inference.pretrained_names():
    # Each network's input from its own name, so the inputs do not depend on which others are
    # shipped (a tree that does not know a later variant lists fewer networks).
    rng = np.random.default_rng([20261201, *f"{name}-{variant}".encode()])
    mcfg, params, _ = inference.load_pretrained(name, variant)
    s = mcfg.setup
    h, w = (-(-n // mcfg.stride) for n in s.grid)                           # the under-scanned grid
    rate = rng.gamma(2.0, 0.5, size=(4, s.num_bins, h, w))
    frames = rng.poisson(rate).astype(np.float32)
    o = inference.run_model(mcfg, params, frames, batch_size=4)
    for k in ("intensity", "depth", "volume"):
      out[f"pretrained/{name}-{variant}/{k}"] = o[k]


def probe_physics(path, out: dict) -> None:
  from nlosjax import physics
  from nlosjax.data.dataset import open_dataset
  with open_dataset(path) as ds:
    name = ds.names("test")[0]
    measurement = np.asarray(ds.read(name, "measurement", 0), np.float32)    # [T, H, W], the full scan
    setup = ds.setup
  for method in ("fbp", "lct", "fk", "phasor", "rsd"):
    out[f"physics/{method}"] = np.asarray(physics.reconstruct(measurement, setup, method))


def probe_main_job(cfg: dict, tmp: pathlib.Path, out: dict) -> None:
  """The main job's command on ``cfg`` (written as a config file), read back from its table."""
  import contextlib
  import io

  from experiments import train as main_job
  config_file = tmp / "probe_config.py"
  config_file.write_text(f"import json\n\ndef get_config():\n  return json.loads({json.dumps(json.dumps(cfg))})\n")
  with contextlib.redirect_stdout(io.StringIO()):
    main_job.main(["--config", str(config_file), "--workdir", str(tmp / "job")])
  table = json.loads((tmp / "job" / "results" / "table.json").read_text())
  for method, metrics in table.items():
    for metric, summary in metrics.items():
      out[f"main_job/{method}/{metric}"] = np.array([summary["mean"], *summary["ci95"]], np.float64)


def main(argv=None) -> int:
  argv = sys.argv[1:] if argv is None else argv
  target = pathlib.Path(argv[0])
  import experiments
  import nlosjax
  out: dict[str, np.ndarray] = {}
  times = {}
  with tempfile.TemporaryDirectory() as d:
    tmp = pathlib.Path(d)
    t0 = time.perf_counter()
    paths = probe_data(tmp, out)
    times["data"] = time.perf_counter() - t0
    cfg, path = paths["lct"]
    t0 = time.perf_counter()
    probe_train_and_evaluate(cfg, path, tmp, out)
    times["train_evaluate"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    probe_physics(path, out)
    times["physics"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    main_cfg = {**cfg, "data": {**cfg["data"], "path": str(tmp / "main_job.h5")}}
    probe_main_job(json.loads(json.dumps(main_cfg)), tmp, out)
    times["main_job"] = time.perf_counter() - t0
  t0 = time.perf_counter()
  probe_pretrained(out)
  times["pretrained"] = time.perf_counter() - t0
  np.savez(target, **out)
  target.with_suffix(".json").write_text(json.dumps(
      {"nlosjax": str(pathlib.Path(nlosjax.__file__).parent),
       "experiments": str(pathlib.Path(experiments.__file__).parent), "seconds": times}, indent=1) + "\n")
  return 0


if __name__ == "__main__":
  sys.exit(main())
