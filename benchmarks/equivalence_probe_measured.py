"""The measured-scan protocol's probe for ``python -m benchmarks.equivalence --probe measured``.

    PYTHONPATH=TREE python benchmarks/equivalence_probe_measured.py OUT.npz

Runs the measured-scan protocol's command line (``python -m
experiments.studies.real_undersampling``; ``experiments.real_undersampling`` before its move)
end to end on one small scan: the shipped exit sign (:func:`nlosjax.data.io.shipped_scan_path`)
with its scan points summed 2 x 2 (32 x 32 points, every raw bin), at strides 4 and 8, with
the shipped ``real`` networks, their ablations and their fits to the scan (``--adapt``), the
binned classic methods, no timing and no in-domain check. Writes to ``OUT.npz`` every number
of its ``--json`` scores (``measured/<section>/...``) and every number in the report's tables
but the seconds (``measured/report/<table>-<row>``), and to ``OUT.json`` which tree ran and how
long it took. A tree without the protocol writes no array (its probes count as added since).
Uses nothing from ``benchmarks``, so it runs on an older tree.
"""

from __future__ import annotations

import contextlib
import io
import json
import pathlib
import re
import sys
import tempfile
import time

import numpy as np

#: A table column holding seconds (left out: they measure the machine, not the code).
TIME_COLUMN = re.compile(r"first|per frame|per scan|seconds")
NUMBER = re.compile(r"-?\d+(?:\.\d+)?(?:e[-+]?\d+)?")
#: JSON keys holding seconds.
TIME_KEYS = {"time_s", "again_s", "timing", "warm"}


def protocol_cli():
  """The protocol's ``__main__`` module at its place in this tree, or None where the tree has none."""
  try:
    from experiments.studies.real_undersampling import __main__ as cli
  except ModuleNotFoundError as e:
    if e.name not in ("experiments.studies", "experiments.studies.real_undersampling"):
      raise
    try:
      from experiments.real_undersampling import __main__ as cli  # before the move
    except ModuleNotFoundError as e:
      if e.name != "experiments.real_undersampling":
        raise
      return None
  return cli


def small_scan(folder: pathlib.Path) -> pathlib.Path:
  """The shipped exit sign with its 64 x 64 scan points summed 2 x 2, as a ``lct_mat`` file in ``folder``."""
  import scipy.io

  from nlosjax.data import io as scan_io
  m = scipy.io.loadmat(scan_io.shipped_scan_path(), variable_names=("rect_data", "width"))
  counts = m["rect_data"].astype(np.uint32)                      # [x, y, t]
  x, y, t = counts.shape
  small = counts.reshape(x // 2, 2, y // 2, 2, t).sum(axis=(1, 3))
  path = folder / "data_exit_sign.mat"
  scipy.io.savemat(path, {"rect_data": np.minimum(small, 65535).astype(np.uint16), "width": m["width"]})
  return path


def json_arrays(value, prefix: str, out: dict, skip=TIME_KEYS) -> None:
  """Every number under ``value`` (nested dicts and lists) into ``out[prefix/...]``; the keys of
  ``skip`` (seconds) left out. Also the studies probe's reader (a sibling script)."""
  if isinstance(value, dict):
    for k, v in value.items():
      if k not in skip:
        json_arrays(v, f"{prefix}/{k}", out, skip)
  elif isinstance(value, list) and all(isinstance(v, (int, float)) for v in value):
    out[prefix] = np.asarray(value, np.float64)
  elif isinstance(value, list):
    for i, v in enumerate(value):
      json_arrays(v, f"{prefix}/{i}", out, skip)
  elif isinstance(value, (int, float)) and not isinstance(value, bool):
    out[prefix] = np.asarray(value, np.float64)


def table_arrays(text: str, out: dict) -> None:
  """Each row of each Markdown table in ``text``: the numbers of its cells, seconds columns left out."""
  table, header, row = -1, None, 0
  for line in text.splitlines():
    if not line.startswith("|"):
      header = None
      continue
    cells = [c.strip() for c in line.strip().strip("|").split("|")]
    if header is None:
      header, table, row = cells, table + 1, 0
      continue
    if not "".join(cells).strip("-: "):
      continue                                                   # the separator row
    numbers = [float(n) for h, c in zip(header, cells) if not TIME_COLUMN.search(h)
               for n in NUMBER.findall(c)]
    if numbers:                                                  # a row of seconds alone: nothing
      out[f"measured/report/{table:02d}-{row:02d}"] = np.asarray(numbers, np.float64)
    row += 1


def repository_arrays(cli) -> dict[str, np.ndarray]:
  """Where the protocol finds the repository and its scans, as numbers (1: yes).

  ``measured/repository/root``: its ``REPO`` is the tree it runs from (the probe runs with the
  tree as its working folder); ``.../shared_scans``: its default scans are the
  ``shared/data/real`` folder beside the tree when one exists, else the shipped scan.
  """
  protocol = sys.modules[f"{cli.__package__}.protocol"]
  tree = pathlib.Path.cwd().resolve()
  shared = tree.parent / "shared" / "data" / "real"
  expected = sorted(shared.glob("*.mat")) if shared.is_dir() else []
  found = [pathlib.Path(f).resolve() for f in protocol.default_files(None)]
  from nlosjax.data import io as scan_io
  return {"measured/repository/root": np.float64(pathlib.Path(protocol.REPO).resolve() == tree),
          "measured/repository/shared_scans": np.float64(
              found == [f.resolve() for f in expected] if expected
              else found == [pathlib.Path(scan_io.shipped_scan_path()).resolve()])}


def main(argv=None) -> int:
  argv = sys.argv[1:] if argv is None else argv
  target = pathlib.Path(argv[0])
  out: dict[str, np.ndarray] = {}
  t0 = time.perf_counter()
  cli = protocol_cli()
  if cli is not None:
    with tempfile.TemporaryDirectory() as d:
      tmp = pathlib.Path(d)
      (tmp / "scans").mkdir()
      small_scan(tmp / "scans")
      with contextlib.redirect_stdout(io.StringIO()):
        cli.main(["--data-dir", str(tmp / "scans"), "--no-timing", "--synthetic", "none", "--adapt",
                  "--json", str(tmp / "scores.json"), "--out", str(tmp / "real.md")])
      for section, value in json.loads((tmp / "scores.json").read_text()).items():
        json_arrays(value, f"measured/{section}", out)
      table_arrays((tmp / "real.md").read_text(), out)
    out.update(repository_arrays(cli))
  save(target, out, {"measured": time.perf_counter() - t0}, protocol=cli is not None)
  return 0


def save(target: pathlib.Path, out: dict, seconds: dict, **meta) -> None:
  """``out`` to ``target`` (``.npz``) and, beside it (``.json``), which tree's packages ran, the
  probes' seconds and ``meta``: what ``benchmarks.equivalence.run_probe`` reads back."""
  import experiments
  import nlosjax
  np.savez(target, **out)
  target.with_suffix(".json").write_text(json.dumps(
      {"nlosjax": str(pathlib.Path(nlosjax.__file__).parent),
       "experiments": str(pathlib.Path(experiments.__file__).parent), **meta, "seconds": seconds},
      indent=1) + "\n")


if __name__ == "__main__":
  sys.exit(main())
