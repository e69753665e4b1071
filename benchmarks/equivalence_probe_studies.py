"""The studies' probes of ``benchmarks.equivalence --probe studies``, run as a script on a tree.

    PYTHONPATH=TREE python benchmarks/equivalence_probe_studies.py OUT.npz

(whichever tree is first on ``sys.path``; ``equivalence_probe_measured.py`` beside it.)

The main probe runs the library and the main job; this one runs the studies' own code
between their designs and the library, so a change there (how a study builds its configs,
hands them to training, scores and records its runs) is judged by the numbers it makes.
Each probe runs a study's own path at the tiny sizes of ``experiments/tiny_run.py`` and
keeps every number of what the study records, times and machine facts aside
(:data:`UNTIMED`). Like the other probes it imports nothing from ``benchmarks`` and uses
interfaces the compared commits share. Probes, each on fixed seeds:

* ``studies/mechanisms``: ``python -m experiments.studies.mechanisms --tiny`` (Ours and
  no-SSM trained to the tiny plateau, tuned and scored on test, the SSM probe of Ours):
  every number of every run's JSON record;
* ``studies/physics_shift``: ``python -m experiments.studies.physics_shift`` on the tiny config
  with one design (``mix``), one variant (Ours-S) and one held-out condition: every number of its
  records (the classic methods tuned and scored on every set, the run trained to the tiny
  plateau and scored on every set);
* ``studies/tradeoff``: the speed-accuracy study's networks (USM, Ours-S, Ours, Ours with
  5 frames) trained 2 steps through its own ``train_learned`` on 5-frame windows: every
  parameter, and the defaults of its command line (so ``tradeoff/__main__.py`` is in the
  closure).
"""

from __future__ import annotations

import contextlib
import io
import json
import pathlib
import sys
import tempfile
import time

import numpy as np

#: Keys of a study's records that hold times, machine facts or paths, not computed numbers.
UNTIMED = frozenset({"time_s", "eval_s", "val_s", "train_wall_s", "wall_s", "seconds", "machine", "date",
                     "data", "path", "commit", "code_digest"})


def leaves(value, prefix: str, out: dict) -> None:
  """Every number of a JSON value into ``out`` by its path, :data:`UNTIMED` keys left out (the
  measured probe's reader: today's, copied beside this script by ``benchmarks.equivalence``)."""
  from equivalence_probe_measured import json_arrays
  json_arrays(value, prefix, out, UNTIMED)


def probe_mechanisms(tmp: pathlib.Path, out: dict) -> None:
  from experiments.studies import mechanisms as M
  results = tmp / "mechanisms-results"
  with contextlib.redirect_stdout(io.StringIO()):
    code = M.main(["--tiny", "--workdir", str(tmp / "mechanisms"), "--results", str(results)])
  if code:
    raise RuntimeError(f"the mechanisms study's --tiny run exited {code}")
  for path in sorted((results / "mechanisms").rglob("*.json")):
    leaves(json.loads(path.read_text()), f"studies/mechanisms/{path.relative_to(results / 'mechanisms')}", out)


def probe_tradeoff(tmp: pathlib.Path, out: dict) -> None:
  import jax

  from experiments.studies.tradeoff import __main__ as cli
  from experiments.studies.tradeoff import training
  from experiments.studies.tradeoff.configs import LEARNED
  from experiments.tiny_run import tiny_config
  from nlosjax import train
  path = tmp / "tradeoff.h5"
  cfg = tiny_config(path, steps=2)
  config = train.RunConfig.from_dict(cfg)
  train.ensure_dataset(config, path, log=lambda s: None)
  setup = config.data.setup()
  window = 5

  def get_loader():
    return train.make_loader(config, path, "train", batch_size=config.train.batch_size, shuffle=True,
                             seed=config.train.seed, window=window)

  # The command line's module is in the closure: its defaults are what `python -m` runs.
  out["studies/tradeoff/cli_defaults"] = np.asarray(
    [cli.FULL_STEPS, cli.QUICK_STEPS, cli.FULL_REPEATS, cli.QUICK_REPEATS, cli.APERTURE], np.float64)
  for spec in LEARNED:
    if spec.name not in ("usm", "ours_s", "ours", "ours_f5"):
      continue
    _, params = training.train_learned(spec, config, setup, tmp / "tradeoff", get_loader, log=lambda s: None)
    for p, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
      out[f"studies/tradeoff/{spec.name}/{jax.tree_util.keystr(p)}"] = np.asarray(leaf)


def probe_physics_shift(tmp: pathlib.Path, out: dict) -> None:
  from experiments.studies.mechanisms import TINY_STOP
  from experiments.studies.physics_shift import heldout
  from experiments.studies.physics_shift.__main__ import main
  from experiments.tiny_run import tiny_config
  cfg = tiny_config(tmp / "physics_shift" / "data" / "tiny.h5", stop=dict(TINY_STOP))
  config_file = tmp / "physics_shift_config.py"
  config_file.write_text(f"import json\n\ndef get_config():\n  return json.loads({json.dumps(json.dumps(cfg))})\n")
  results = tmp / "physics_shift-results"
  with contextlib.redirect_stdout(io.StringIO()):
    main(["--config", str(config_file), "--designs", "mix", "--variants", "ours_s", "--conditions",
          sorted(heldout.CONDITIONS)[0], "--workdir", str(tmp / "physics_shift"), "--results", str(results)])
  for path in sorted((results / "physics_shift").glob("*.json")):
    leaves(json.loads(path.read_text()), f"studies/physics_shift/{path.stem}", out)


PROBES = {"mechanisms": probe_mechanisms, "tradeoff": probe_tradeoff, "physics_shift": probe_physics_shift}


def main(argv=None) -> int:
  argv = sys.argv[1:] if argv is None else argv
  from equivalence_probe_measured import save
  out: dict[str, np.ndarray] = {}
  times = {}
  with tempfile.TemporaryDirectory() as d:
    for name, probe in PROBES.items():
      t0 = time.perf_counter()
      probe(pathlib.Path(d), out)
      times[name] = time.perf_counter() - t0
  save(pathlib.Path(argv[0]), out, times)
  return 0


if __name__ == "__main__":
  sys.exit(main())
