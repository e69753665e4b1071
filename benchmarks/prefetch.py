"""Reading batches ahead while the step runs (``data.loader.prefetch``): ``benchmarks/results/prefetch.md``.

    python -m benchmarks.prefetch [--config cpu] [--steps 40] [--rounds 2] [--ahead 2]

Trains the preset's Ours from scratch for ``--steps`` steps with its data read from disk at
every step (``in_memory`` false, as the paper preset reads its 1 GiB sequences), once reading
each batch when the step needs it (``prefetch`` 0) and once ``--ahead`` batches ahead in a
thread, alternating over ``--rounds`` rounds so both see the same machine. Reported: the
time to read one batch from disk alone, and each setting's seconds per step after the first
``--steps // 4`` (compilation and warm-up left out), with their ratio. The two settings train
on the same batches, so their parameters agree bit for bit (checked here too).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import statistics
import sys
import tempfile
import time

from nlosjax.variants import OURS

ROOT = pathlib.Path(__file__).resolve().parent.parent
DEFAULT_OUT = ROOT / "benchmarks" / "results" / "prefetch.md"


def read_time(config: dict, data_path, batches: int = 20) -> float:
  """Median seconds to read one training batch from disk (``TripletLoader.batch``, not in memory)."""
  from nlosjax import train as T
  cfg = {**config, "data": {**config["data"], "loader": {**config["data"].get("loader", {}), "in_memory": False}}}
  loader = T.make_loader(T.RunConfig.from_dict(cfg), data_path, "train", batch_size=int(config["train"]["batch_size"]),
                         shuffle=True, seed=0)
  try:
    times = []
    for k in range(batches):
      t0 = time.perf_counter()
      loader.batch(k)
      times.append(time.perf_counter() - t0)
  finally:
    loader.close()
  return statistics.median(times)


def train_seconds_per_step(config: dict, data_path, workdir: pathlib.Path, ahead: int, steps: int):
  """``(seconds per step after the first steps // 4, final parameters)`` of a fresh run reading from disk."""
  from nlosjax import train as T
  cfg = json.loads(json.dumps(config))
  cfg["data"]["loader"] = {**cfg["data"].get("loader", {}), "in_memory": False, "prefetch": ahead}
  skip = max(1, steps // 4)
  cfg["train"].update(steps=steps, log_every=1, checkpoint_every=steps, select_checkpoint="last",
                      variants=[OURS])
  cfg["train"].pop("stop", None)
  cfg = T.RunConfig.from_dict(cfg)
  _, state = T.train_model(cfg, data_path, workdir, OURS, log=lambda s: None)
  rows = [json.loads(line) for line in (workdir / OURS / "metrics.jsonl").read_text().splitlines()]
  t = {r["step"]: r["time_s"] for r in rows}
  return (t[steps] - t[skip]) / (steps - skip), T.to_host(state.params)


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--config", default="cpu")
  parser.add_argument("--steps", type=int, default=40)
  parser.add_argument("--rounds", type=int, default=2)
  parser.add_argument("--ahead", type=int, default=2)
  parser.add_argument("--out", default=str(DEFAULT_OUT))
  args = parser.parse_args(argv)
  if args.steps < 8 or args.rounds < 1 or args.ahead < 1:
    parser.error("--steps >= 8, --rounds >= 1 and --ahead >= 1 are needed")
  import jax
  import numpy as np

  from experiments import provenance as _machine
  from experiments.cli import load_config
  from nlosjax import train as T
  config = load_config(args.config)
  data_path = pathlib.Path(config["data"]["path"])
  T.ensure_dataset(T.RunConfig.from_dict(config), data_path)
  read_s = read_time(config, data_path)
  per_step = {0: [], args.ahead: []}
  params = {}
  with tempfile.TemporaryDirectory() as tmp:
    for r in range(args.rounds):
      for ahead in ((0, args.ahead) if r % 2 == 0 else (args.ahead, 0)):
        s, params[ahead] = train_seconds_per_step(config, data_path, pathlib.Path(tmp) / f"r{r}-p{ahead}",
                                                  ahead, args.steps)
        per_step[ahead].append(s)
        print(f"round {r}: prefetch {ahead}: {s:.3f} s/step", flush=True)
  same = all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(params[0]), jax.tree.leaves(params[args.ahead])))
  base, fast = statistics.median(per_step[0]), statistics.median(per_step[args.ahead])
  command = "python -m benchmarks.prefetch " + " ".join(sys.argv[1:] if argv is None else argv)
  lines = ["# Reading batches ahead while the step runs", ""]
  lines += _machine.provenance(command.strip()) + [""]
  lines += [f"The `{args.config}` preset's Ours trained from scratch for {args.steps} steps of batch "
            f"{config['train']['batch_size']}, its data read from disk at every step (`in_memory` false; "
            f"`{data_path}`), alternating the two settings over {args.rounds} rounds. Seconds per step after "
            f"the first {max(1, args.steps // 4)} steps (compilation and warm-up left out); medians over rounds.",
            "",
            "| setting | s / step (each round) | s / step (median) |", "|---|---|---|",
            f"| prefetch 0 (read when needed) | {', '.join(f'{v:.3f}' for v in per_step[0])} | {base:.3f} |",
            f"| prefetch {args.ahead} (read ahead in a thread) | "
            f"{', '.join(f'{v:.3f}' for v in per_step[args.ahead])} | {fast:.3f} |", "",
            f"- Reading one batch from disk alone: {1000 * read_s:.1f} ms (median of 20), "
            f"{100 * read_s / base:.1f} % of a step read in turn.",
            f"- Prefetch {args.ahead} over prefetch 0: {fast / base:.3f}x the time per step "
            f"({100 * (base - fast) / base:+.1f} % of the step saved).",
            f"- Final parameters of the two settings {'identical bit for bit' if same else 'DIFFER'} "
            "(the same batches in the same order)."]
  text = "\n".join(lines) + "\n"
  pathlib.Path(args.out).write_text(text)
  print(text)
  return 0 if same else 1


if __name__ == "__main__":
  sys.exit(main())
