"""Data regenerated on another CPU model: a fingerprint that float rounding leaves within tolerance.

XLA:CPU rounds differently at another vector width, so a dataset regenerated from its
spec on another CPU model has another content digest. ``dataset_fingerprint`` must take
such a file as the same data and refuse any other. The default tier checks it against
hand-made files (cell sums by a brute-force loop, rounding and one-count perturbations,
a changed frame); the full tier regenerates the tiny dataset with XLA's SSE4.2 code in a
subprocess, as another machine would, and resumes a run on it.
"""

import itertools
import json
import os
import pathlib
import shutil
import subprocess
import sys

import h5py
import numpy as np
import pytest

from nlosjax.data import dataset as D
from nlosjax.data.dataset import file as dataset_file
from nlosjax.train import RunConfig, run_state

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _write(path, arrays):
  with h5py.File(path, "w") as f:
    for name, x in arrays.items():
      f.create_dataset(name, data=x)
  return path


def _arrays(seed=0):
  rng = np.random.default_rng(seed)
  # A small sequence (4 frames of 64 bins at 8 x 8, about 1e5 counts), like the tiny dataset's.
  clean = rng.gamma(2.0, 3.0, size=(4, 64, 8, 8)).astype(np.float32)
  return {"sequences/train-00000/clean": clean,
          "sequences/train-00000/measurement": rng.poisson(clean).astype(np.float32),
          "sequences/train-00000/depth": rng.uniform(0.5, 1.5, size=(4, 8, 8)).astype(np.float32),
          "sequences/train-00000/trajectory": rng.normal(size=(4, 2, 3)).astype(np.float32)}


def test_cell_sums_are_the_sums_over_each_half_of_every_axis_by_a_loop():
  x = np.random.default_rng(1).normal(size=(3, 5, 2, 1))
  got = dataset_file._cell_sums(x, 2)
  # Brute force: each axis of n cut at round(n / 2) (an axis of 1 is one slab), cells in C order.
  cuts = [[(0, n)] if n < 2 else [(0, int(round(n / 2))), (int(round(n / 2)), n)] for n in x.shape]
  want = []
  for cell in itertools.product(*cuts):
    total = 0.0
    for index in itertools.product(*[range(a, b) for a, b in cell]):
      total += x[index]
    want.append(total)
  np.testing.assert_allclose(got, want, rtol=1e-12)
  assert dataset_file._cell_sums(np.float32(2.5), 2) == [2.5]


def test_rounding_and_a_few_flipped_counts_pass_and_other_data_are_named(tmp_path):
  arrays = _arrays()
  a = _write(tmp_path / "a.h5", arrays)
  # Another machine: a few noise-free values one or two ulps off, one count drawn one higher.
  rounded = {k: v.copy() for k, v in arrays.items()}
  clean = rounded["sequences/train-00000/clean"].reshape(-1)
  for i in (3, 50, 400):
    clean[i] = np.nextafter(np.nextafter(clean[i], np.inf), np.inf)
  rounded["sequences/train-00000/measurement"].reshape(-1)[7] += 1
  b = _write(tmp_path / "b.h5", rounded)
  assert D.dataset_digest(a) != D.dataset_digest(b)
  fa, fb = D.dataset_fingerprint(a), D.dataset_fingerprint(b)
  assert D.fingerprint_differences(fa, fb) == []
  assert 0 < D.fingerprint_distance(fa, fb) < D.FINGERPRINT_RTOL
  # Other data: one frame 5 % brighter, another seed, a missing array, another shape.
  brighter = {k: v.copy() for k, v in arrays.items()}
  brighter["sequences/train-00000/measurement"][1] *= 1.05
  differ = D.fingerprint_differences(fa, D.dataset_fingerprint(_write(tmp_path / "c.h5", brighter)))
  assert len(differ) == 1 and differ[0].startswith("sequences/train-00000/measurement: cell sums differ")
  other = D.fingerprint_differences(fa, D.dataset_fingerprint(_write(tmp_path / "d.h5", _arrays(seed=1))))
  assert len(other) == 4
  fewer = {k: v for k, v in arrays.items() if not k.endswith("depth")}
  assert D.fingerprint_differences(fa, D.dataset_fingerprint(_write(tmp_path / "e.h5", fewer))) == [
      "sequences/train-00000/depth: recorded, not in these data"]
  shorter = {**arrays, "sequences/train-00000/depth": arrays["sequences/train-00000/depth"][:2]}
  assert D.fingerprint_differences(fa, D.dataset_fingerprint(_write(tmp_path / "f.h5", shorter))) == [
      "sequences/train-00000/depth: shape [4, 8, 8] recorded, [2, 8, 8] now"]
  # A zero-photon sequence has no mass: equal is equal, anything else differs.
  zeros = _write(tmp_path / "z.h5", {"m": np.zeros((2, 3), np.float32)})
  assert D.fingerprint_differences(D.dataset_fingerprint(zeros), D.dataset_fingerprint(zeros)) == []
  one = _write(tmp_path / "o.h5", {"m": np.eye(2, 3, dtype=np.float32)})
  assert D.fingerprint_differences(D.dataset_fingerprint(zeros), D.dataset_fingerprint(one))
  with pytest.raises(ValueError, match="rtol"):
    D.fingerprint_differences(fa, fb, rtol=float("nan"))


def test_dataset_identity_is_digest_and_fingerprint_from_one_read_and_cached(tmp_path):
  path = _write(tmp_path / "a.h5", {**_arrays(), "attrs/scalar": np.float64(3.0), "attrs/name": b"cpu"})
  # The chunked digest (a row at a time) and the fingerprint read separately are the reference.
  want = (D.dataset_digest(path, chunk_bytes=1), D.dataset_fingerprint(path))
  assert D.dataset_identity(path, cache=False) == want
  assert not (tmp_path / "a.h5.digest.json").exists()
  assert D.dataset_identity(path) == want
  cache = tmp_path / "a.h5.digest.json"
  saved = json.loads(cache.read_text())
  # An unchanged file is answered from the cache (a marked entry, checksummed, comes back) ...
  marked = {**saved, "digest": "from-cache"}
  marked["checksum"] = dataset_file._cache_checksum(marked)
  cache.write_text(json.dumps(marked))
  assert D.dataset_identity(path)[0] == "from-cache"
  # ... an entry whose checksum no longer matches (damaged) is not believed: the file is read again ...
  cache.write_text(json.dumps({**marked, "digest": "damaged"}))
  assert D.dataset_identity(path) == want
  # ... another file under the same name is read again, and a broken cache is rewritten.
  _write(path, _arrays(seed=3))
  assert D.dataset_identity(path)[0] == D.dataset_digest(path) != want[0]
  cache.write_text("{not json")
  assert D.dataset_identity(path)[0] == D.dataset_digest(path)


def test_check_data_takes_rounding_refuses_other_data_and_old_exports(tmp_path):
  arrays = _arrays()
  recorded = D.dataset_fingerprint(_write(tmp_path / "a.h5", arrays))
  nearby = {name: {**v, "cells": [c * (1 + 1e-7) for c in v["cells"]]} for name, v in recorded.items()}
  far = D.dataset_fingerprint(_write(tmp_path / "b.h5", _arrays(seed=2)))
  folder = tmp_path / "export"
  folder.mkdir()
  meta = {"data_digest": "aaaa"}
  # Nothing recorded yet: only the digest can be compared.
  assert run_state.check_data(folder, meta, "aaaa", None) == ("digest", None)
  with pytest.raises(ValueError, match="digest aaaa.*bbbb.*--allow-data-change.*records no data fingerprint"):
    run_state.check_data(folder, meta, "bbbb", nearby)
  assert run_state.check_data(folder, meta, "bbbb", nearby, allow_data_change=True).kind == "allowed change"
  (folder / run_state.FINGERPRINT_FILE).write_text(json.dumps(recorded))
  assert run_state.read_fingerprint(folder) == recorded
  check = run_state.check_data(folder, meta, "bbbb", nearby)
  assert check.kind == "rounding" and 0 < check.distance < D.FINGERPRINT_RTOL
  assert check.describe().startswith("; data regenerated with another rounding (fingerprint within ")
  with pytest.raises(ValueError, match="beyond rounding:\n  sequences/train-00000/"):
    run_state.check_data(folder, meta, "bbbb", far)
  with pytest.raises(ValueError, match="computed no data fingerprint"):
    run_state.check_data(folder, meta, "bbbb", None)


_REGENERATE = """
import pathlib, sys
sys.path.insert(0, {root!r})
from nlosjax import train as T
from tests.tiny_run import tiny_config
path = pathlib.Path({path!r})
T.ensure_dataset(T.RunConfig.from_dict(tiny_config(path)), path, log=lambda s: None)
"""


@pytest.mark.full
def test_a_run_resumes_on_data_regenerated_with_another_vector_width(tmp_path_factory, tmp_path):
  """The tiny dataset made again with XLA's SSE4.2 code (another machine's rounding) resumes a run."""
  from nlosjax import train as T
  from tests.tiny_run import make_tiny_dataset, tiny_config
  here = make_tiny_dataset(tmp_path_factory)
  there = tmp_path / "regenerated" / "tiny.h5"
  there.parent.mkdir()
  env = {**os.environ, "XLA_FLAGS": (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_max_isa=SSE4_2").strip(),
         "JAX_PLATFORMS": "cpu"}
  subprocess.run([sys.executable, "-c", _REGENERATE.format(root=str(ROOT), path=str(there))],
                 check=True, env=env, cwd=ROOT, timeout=900)
  fp_here, fp_there = D.dataset_fingerprint(here), D.dataset_fingerprint(there)
  assert D.fingerprint_differences(fp_here, fp_there) == []
  same_bits = D.dataset_digest(here) == D.dataset_digest(there)
  # Measured on AVX-512 and AVX2 machines: the noise-free transients differ in a few hundred
  # values by rounding (0 if this machine's XLA already emits SSE4.2-width code).
  assert same_bits or D.fingerprint_distance(fp_here, fp_there) > 0
  cfg = tiny_config(here, steps=4)
  quiet = lambda s: None  # noqa: E731
  # An unfinished run (a finished one exports its chosen parameters alone): paused after step 1.
  export = T.StateExport(tmp_path / "state", data_digest=D.dataset_digest(here), data_fingerprint=fp_here,
                         deadline=0.0)
  with pytest.raises(T.TrainingPaused):
    T.train_model(RunConfig.from_dict(cfg), here, tmp_path / "a", "ours_s", log=quiet, export=export)
  assert run_state.read_fingerprint(tmp_path / "state/ours_s") == fp_here
  # A fresh clone on the other machine: the export copied, its data regenerated there.
  shutil.copytree(tmp_path / "state", tmp_path / "clone")
  messages = []
  moved = T.StateExport(tmp_path / "clone", data_digest=D.dataset_digest(there), data_fingerprint=fp_there)
  _, state = T.train_model(RunConfig.from_dict(tiny_config(there, steps=4)), there, tmp_path / "b", "ours_s",
                           log=messages.append, export=moved)
  assert int(state.step) == 4
  resumed = [m for m in messages if "resumed from step 1 of the exported state" in m]
  assert resumed and (same_bits or "another rounding" in resumed[0])
