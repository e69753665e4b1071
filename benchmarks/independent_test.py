"""Evaluate a trained run on test sequences made by an independent generator.

    python -m benchmarks.independent_test [--checkpoint runs/default] [--sequences 8]
        [--frames 8] [--seed 2026] [--data runs/data/independent.h5]
        [--out benchmarks/results/table1_independent.md]

The main job's test split comes from the same generator as its training
split (``nlosjax.data.scenes``: letters, digits, polygons, plates, boxes,
spheres, tori, bars on helices). This script writes a test file *without*
that generator, with plain h5py in the documented layout (README, "Dynamic
NLOS dataset"), from other shapes and other motions:

* shapes: fronto-parallel rings, crosses, ellipses, triangles and L-shapes,
  rasterised on the scan grid with 4 x 4 sub-pixel coverage, uniform or
  radial-gradient albedo;
* motion: the dynamic object moves on a straight line that bounces off the
  edges of a 0.9 m square, while its depth oscillates sinusoidally (no helix);
  one or two static objects;
* the same Setup and detector model as the run's config (efficiency, photon
  budget, ambient, dark counts, jitter drawn from the config's ranges);
  measurement = Poisson counts of ``add_spad_noise`` on ``render`` of the
  albedo volume.

Then it evaluates the run's checkpoints and every classic method on the file
(:func:`nlosjax.evaluation.protocol.evaluate`, the same code as
``experiments.evaluate``; classic settings as the run chose them on its
validation split) and writes the table with intervals over sequences to
``--out`` (and ``.json``).
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys
import time

import h5py
import numpy as np

SHAPES = ("ring", "cross", "ellipse", "triangle", "ell")


def shape_mask(kind: str, u: np.ndarray, v: np.ndarray, size: float, angle: float) -> np.ndarray:
  """Boolean mask of a planar shape of extent ``size`` (m) at local coords ``u, v`` (m)."""
  c, s = math.cos(angle), math.sin(angle)
  p, q = c * u + s * v, -s * u + c * v
  r = size / 2
  if kind == "ring":
    d = np.hypot(p, q)
    return (d <= r) & (d >= 0.55 * r)
  if kind == "cross":
    w = 0.3 * r
    return ((np.abs(p) <= r) & (np.abs(q) <= w)) | ((np.abs(q) <= r) & (np.abs(p) <= w))
  if kind == "ellipse":
    return (p / r) ** 2 + (q / (0.55 * r)) ** 2 <= 1
  if kind == "triangle":        # equilateral, pointing up in the rotated frame
    return (q >= -0.5 * r) & (q <= r - math.sqrt(3) * np.abs(p))
  if kind == "ell":
    w = 0.35 * r
    return ((np.abs(p) <= r) & (q >= -r) & (q <= -r + 2 * w)) | \
           ((p >= -r) & (p <= -r + 2 * w) & (np.abs(q) <= r))
  raise ValueError(f"kind must be one of {SHAPES}, got {kind!r}")


def make_sequence(rng: np.random.Generator, setup, frames: int, *, supersample: int = 4) -> dict:
  """Albedo volumes ``[F, T, H, W]``, intensity and depth ``[F, H, W]`` of one scene."""
  H, W = setup.grid
  dz = setup.depth_bin_length
  sub = (np.arange(supersample) + 0.5) / supersample - 0.5
  ys = (setup.scan_y[:, None] + sub[None, :] * setup.spacing[0]).reshape(-1)    # [H s]
  xs = (setup.scan_x[:, None] + sub[None, :] * setup.spacing[1]).reshape(-1)    # [W s]
  Y, X = np.meshgrid(ys, xs, indexing="ij")
  objects = []
  for k in range(int(rng.integers(1, 3)) + 1):          # 1-2 static + the dynamic one (last)
    objects.append(dict(kind=str(rng.choice(SHAPES)), size=float(rng.uniform(0.25, 0.5)),
                        angle=float(rng.uniform(0, 2 * np.pi)),
                        albedo=float(rng.uniform(0.4, 1.0)), gradient=bool(rng.random() < 0.5),
                        pos=rng.uniform(-0.35, 0.35, 2), z=float(rng.uniform(0.6, 1.4))))
  dyn = objects[-1]
  velocity = rng.uniform(0.05, 0.15, 2) * rng.choice([-1, 1], 2)      # m per frame
  z_amp, z_freq = float(rng.uniform(0.05, 0.2)), float(rng.uniform(0.2, 0.6))
  spin = float(rng.uniform(-0.3, 0.3))                                # rad per frame
  vol = np.zeros((frames, setup.num_bins, H, W), np.float32)
  inten = np.zeros((frames, H, W), np.float32)
  depth = np.zeros((frames, H, W), np.float32)
  for f in range(frames):
    zbuf = np.full(Y.shape, np.inf)
    alb = np.zeros(Y.shape)
    for i, o in enumerate(objects):
      pos, z, angle = o["pos"], o["z"], o["angle"]
      if i == len(objects) - 1:                           # bounce inside |x|, |y| <= 0.45
        pos = pos + velocity * f
        pos = 0.45 - np.abs((pos + 0.45) % 1.8 - 0.9)
        z = z + z_amp * math.sin(z_freq * f)
        angle = angle + spin * f
      m = shape_mask(o["kind"], X - pos[1], Y - pos[0], o["size"], angle)
      a = o["albedo"] * (1 - 0.6 * np.hypot(X - pos[1], Y - pos[0]) / o["size"] if o["gradient"] else 1)
      hit = m & (z < zbuf)
      zbuf = np.where(hit, z, zbuf)
      alb = np.where(hit, np.clip(a, 0.1, 1.0), alb)
    hit = np.isfinite(zbuf)
    bins = np.where(hit, np.floor(zbuf / dz), 0).astype(int)
    rows = np.repeat(np.arange(H), supersample)[:, None].repeat(W * supersample, 1)
    cols = np.repeat(np.arange(W), supersample)[None, :].repeat(H * supersample, 0)
    np.add.at(vol[f], (bins[hit], rows[hit], cols[hit]), alb[hit] / supersample ** 2)
    pix = lambda a: a.reshape(H, supersample, W, supersample).mean(axis=(1, 3))
    cover = pix(hit.astype(float))
    shaded = pix(alb)
    inten[f] = shaded / shaded.max() if shaded.max() > 0 else 0
    zsum = pix(np.where(hit, zbuf, 0.0))
    depth[f] = np.where(cover > 0, zsum / np.maximum(cover, 1e-12), 0.0)
  return {"albedo": vol, "intensity": inten, "depth": depth}


def write_testset(path: pathlib.Path, data: dict, sequences: int, frames: int, seed: int) -> None:
  """Write ``sequences`` test sequences in the documented layout (plain h5py)."""
  import jax
  from nlosjax.data.dataset import DatasetSpec
  from nlosjax.physics import add_spad_noise, render
  from tqdm import tqdm
  setup = DatasetSpec.from_config(data).setup
  rng = np.random.default_rng(seed)
  tmp = path.with_suffix(path.suffix + ".partial")
  path.parent.mkdir(parents=True, exist_ok=True)
  T = setup.num_bins
  with h5py.File(tmp, "w") as f:
    a = f.attrs
    a.update({"format": "nlosjax-dynamic-nlos", "format_version": 1,
              "generator_version": "benchmarks.independent_test", "wall_size": setup.wall_size,
              "grid": np.asarray(setup.grid), "bin_width": setup.bin_width, "num_bins": T,
              "seed": seed, "num_train": 0, "num_test": sequences, "background_depth": 0.0,
              "complete": False})
    group = f.create_group("sequences")
    for i in tqdm(range(sequences), desc="independent test sequences", unit="seq"):
      scene = make_sequence(rng, setup, frames)
      clean = np.asarray(render(scene["albedo"], setup))
      photons = float(np.exp(rng.uniform(*np.log(data["photons"]))))
      clean = clean * np.float32(photons / float(np.mean(np.sum(clean, axis=1))))
      efficiency = float(rng.uniform(*data["efficiency"]))
      ambient = float(np.exp(rng.uniform(*np.log(data["ambient"])))) / T
      key = jax.random.key(seed * 1000 + i)
      counts = np.stack([np.asarray(add_spad_noise(
          jax.random.fold_in(key, k), clean[k], setup, pulses=1.0, efficiency=efficiency,
          ambient=ambient, dark_counts=float(data["dark_counts"]) / T, jitter=data["jitter"]))
          for k in range(frames)])
      g = group.create_group(f"test-{i:05d}")
      g.attrs.update({"split": "test", "index": i, "efficiency": efficiency, "photons": photons})
      g["measurement"] = counts.astype(np.uint32)
      g["clean"] = clean.astype(np.float32)
      g["intensity"] = scene["intensity"]
      g["depth"] = scene["depth"]
    a["complete"] = True
  tmp.replace(path)


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--checkpoint", default="runs/default")
  parser.add_argument("--sequences", type=int, default=8)
  parser.add_argument("--frames", type=int, default=8)
  parser.add_argument("--seed", type=int, default=2026)
  parser.add_argument("--data", default="runs/data/independent.h5")
  parser.add_argument("--out", default="benchmarks/results/table1_independent.md")
  args = parser.parse_args(argv)
  from nlosjax import checkpoints_io
  from nlosjax import train as T
  from nlosjax.evaluation import protocol, report
  from benchmarks._machine import provenance
  t0 = time.perf_counter()
  config, trained = checkpoints_io.load_run(args.checkpoint)
  config = T.with_defaults(config)
  data = pathlib.Path(args.data)
  if not data.exists():
    write_testset(data, config["data"], args.sequences, args.frames, args.seed)
  chosen = pathlib.Path(args.checkpoint) / "results" / "validation.json"
  choices = json.loads(chosen.read_text()) if chosen.exists() else {}
  settings, best = choices.get("classic", {}), choices.get("best_classic")
  evaluation = protocol.evaluate(config, data, trained, classic_settings=settings)
  table, comparisons = protocol.tabulate(evaluation, best_classic_method=best)
  cmd = "python -m benchmarks.independent_test " + " ".join(sys.argv[1:] if argv is None else argv)
  where = (f"the settings the run chose on its validation split (`{chosen}`)" if settings
           else "their defaults (the run recorded no validation choices)")
  caption = (f"Models from `{args.checkpoint}` (the main job's CPU preset; each variant's "
             f"checkpoint chosen on validation), evaluated on {args.sequences} sequences x "
             f"{args.frames} frames written by this script's own generator (rings, crosses, "
             "ellipses, triangles, L-shapes; bouncing linear motion with depth oscillation; no "
             "helix), the run's Setup and detector ranges; classic methods on the interpolated "
             f"under-scanned input with {where}. Nothing is chosen on this file. "
             f"{time.perf_counter() - t0:.0f} s.")
  out = pathlib.Path(args.out)
  out.parent.mkdir(parents=True, exist_ok=True)
  text = ["# Table 1 on independently generated test sequences", ""] + provenance(cmd.strip()) + [""]
  body = report.format_tables(table, caption)
  if comparisons:
    body += "\n" + report.format_comparisons(comparisons)
  out.write_text("\n".join(text) + "\n" + body)
  out.with_suffix(".json").write_text(json.dumps({"table": table, "comparisons": comparisons},
                                                 indent=2) + "\n")
  from nlosjax.evaluation.figures import plot_comparison
  plot_comparison(evaluation["images"], out.with_name(out.stem + "_comparison.png"))
  print(out.read_text())


if __name__ == "__main__":
  main()
