"""The HDF5 file format (layout in the :mod:`nlosjax.data.dataset` docstring): writer and reader.

Writing (:func:`write_dataset`, :func:`extend_dataset`): sequences go to
``<path>.partial``, flushed one by one (a rerun resumes it), simulated here
or in ``spawn``ed worker processes (:func:`_simulate_job`), and the file is
renamed to ``path`` when complete. Reading: :class:`DynamicDataset`
(:func:`open_dataset`) checks the format, version and Setup and reads
frames, under-scanned row by row.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import datetime
import hashlib
import json
import math
import multiprocessing
import os
import pathlib
import shutil
import warnings

import h5py
import numpy as np

from nlosjax import files
from nlosjax.data import scenes
from nlosjax.data.dataset.simulate import simulate_sequence
from nlosjax.data.dataset.spec import SPLITS, DatasetSpec, _check_split, sequence_name
from nlosjax.data.dataset.undersampling import _check_stride
from nlosjax.physics.setup import Setup

#: Value of the root ``format`` attribute.
FORMAT_NAME = "nlosjax-dynamic-nlos"
#: Layout version; readers refuse newer files.
FORMAT_VERSION = 1
#: Per-sequence datasets: name -> whether every file has it.
DATASETS = {"measurement": True, "clean": False, "albedo": False, "intensity": True,
            "depth": True, "trajectory": True}
#: HDF5 format bounds of the files written: 1.10's object headers, chunk indexes and superblock carry
#: checksums (the earliest format's do not, and a flipped bit there went unnoticed), and HDF5 1.10 or
#: newer reads them.
LIBVER = ("v110", "v110")
#: Attribute holding a digest of its object's other attributes (the root's and each sequence's):
#: string attributes live in HDF5's global heap, which no checksum covers. Checked on opening.
ATTRS_DIGEST = files.ATTRS_DIGEST
attrs_digest = files.attrs_digest
_seal = files.seal_attrs
_attrs_intact = files.attrs_intact


#: Bytes reserved on disk beyond a step's arrays, for HDF5's metadata (:func:`nlosjax.files.reserve`).
RESERVE_MARGIN = 1 << 20


def _hdf5_end(path: pathlib.Path) -> int | None:
  """HDF5's end of file as its superblock records it (at the last flush), or None where unknown.

  (h5py's ``get_filesize`` gives the larger of that and the file's size, so it cannot tell the
  space :func:`reserve_space` set aside from the space HDF5 uses.)
  """
  with open(path, "rb") as fh:
    head = fh.read(96)
  if len(head) < 16 or head[:8] != _HDF5_SIGNATURE:
    return None
  version = head[8]
  if version in (2, 3):
    size, at = head[9], 12
  elif version in (0, 1):
    size, at = head[13], 24 if version == 0 else 28
  else:
    return None
  if size not in (4, 8) or len(head) < at + 3 * size:
    return None
  base = int.from_bytes(head[at:at + size], "little")
  end = int.from_bytes(head[at + 2 * size:at + 3 * size], "little")
  return base + end


def reserve_space(f: h5py.File, tmp: pathlib.Path, nbytes: int = 0) -> None:
  """Reserve on disk what the next step writes (``nbytes`` of arrays and a margin) past HDF5's end of file.

  A full disk then fails in :func:`nlosjax.files.reserve`, cleanly, and not inside HDF5, which
  crashes the process when a write fails. Called after a flush (the superblock then holds HDF5's
  end of file).
  """
  end = _hdf5_end(tmp)
  files.reserve(tmp, tmp.stat().st_size if end is None else end, int(nbytes * 1.05) + RESERVE_MARGIN)


def trim_reserved(tmp: pathlib.Path) -> None:
  """Cut the space reserved but not used off a closed file (past HDF5's end of file)."""
  end = _hdf5_end(tmp)
  if end is not None and tmp.stat().st_size > end:
    os.truncate(tmp, end)


def _lookup3(data: bytes, initval: int = 0) -> int:
  """Bob Jenkins' lookup3 ``hashlittle``: the checksum HDF5 puts on its metadata (``H5_checksum_lookup3``)."""
  def rot(x, k):
    return ((x << k) | (x >> (32 - k))) & 0xFFFFFFFF

  m = 0xFFFFFFFF
  n = len(data)
  a = b = c = (0xDEADBEEF + n + initval) & m
  i = 0
  word = lambda j: int.from_bytes(data[j:j + 4], "little")          # noqa: E731
  while n > 12:
    a, b, c = (a + word(i)) & m, (b + word(i + 4)) & m, (c + word(i + 8)) & m
    a = (a - c) & m; a ^= rot(c, 4); c = (c + b) & m                 # noqa: E702
    b = (b - a) & m; b ^= rot(a, 6); a = (a + c) & m                 # noqa: E702
    c = (c - b) & m; c ^= rot(b, 8); b = (b + a) & m                 # noqa: E702
    a = (a - c) & m; a ^= rot(c, 16); c = (c + b) & m                # noqa: E702
    b = (b - a) & m; b ^= rot(a, 19); a = (a + c) & m                # noqa: E702
    c = (c - b) & m; c ^= rot(b, 4); b = (b + a) & m                 # noqa: E702
    n -= 12
    i += 12
  if n == 0:
    return c
  tail = data[i:] + bytes(12 - n)
  a = (a + int.from_bytes(tail[0:4], "little")) & m
  b = (b + int.from_bytes(tail[4:8], "little")) & m
  c = (c + int.from_bytes(tail[8:12], "little")) & m
  c ^= b; c = (c - rot(b, 14)) & m                                   # noqa: E702
  a ^= c; a = (a - rot(c, 11)) & m                                   # noqa: E702
  b ^= a; b = (b - rot(a, 25)) & m                                   # noqa: E702
  c ^= b; c = (c - rot(b, 16)) & m                                   # noqa: E702
  a ^= c; a = (a - rot(c, 4)) & m                                    # noqa: E702
  b ^= a; b = (b - rot(a, 14)) & m                                   # noqa: E702
  c ^= b; c = (c - rot(b, 24)) & m                                   # noqa: E702
  return c


_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def _clear_write_flag(tmp: pathlib.Path) -> bool:
  """Clear the "open for writing" flag a killed writer leaves in the file's superblock; True if cleared.

  HDF5 1.10's superblock (versions 2 and 3, :data:`LIBVER`) records that a writer has the file
  open, and refuses to open a file whose writer died ("file is already open for write"; HDF5's
  ``h5clear`` tool clears it). Called only where no process holds the file's lock. Touches
  nothing unless the superblock's own checksum is intact before the change.
  """
  with open(tmp, "r+b") as f:
    head = f.read(64)
    if len(head) < 12 or head[:8] != _HDF5_SIGNATURE or head[8] not in (2, 3) or head[11] == 0:
      return False
    end = 12 + 4 * head[9]
    if len(head) < end + 4 or int.from_bytes(head[end:end + 4], "little") != _lookup3(head[:end]):
      return False
    cleared = head[:11] + b"\0" + head[12:end]
    f.seek(0)
    f.write(cleared + _lookup3(cleared).to_bytes(4, "little"))
  return True


def _unlocked(tmp: pathlib.Path) -> bool:
  """Whether no process holds the file lock HDF5 takes on ``tmp`` (probed with ``flock``, released at once)."""
  import fcntl
  fd = os.open(tmp, os.O_RDONLY)
  try:
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
  except BlockingIOError:
    return False
  finally:
    os.close(fd)                       # closing releases the probe's lock
  return True


def _seal(obj) -> None:
  """Write the digest of ``obj``'s attributes, read back as a reader reads them."""
  obj.attrs[ATTRS_DIGEST] = attrs_digest(obj.attrs)


def _attrs_intact(obj) -> bool | None:
  """Whether ``obj``'s attributes match their digest (None: written before digests existed)."""
  if ATTRS_DIGEST not in list(obj.attrs):       # listing raises where HDF5's checksum fails
    return None
  recorded = obj.attrs[ATTRS_DIGEST]
  if isinstance(recorded, bytes):
    recorded = recorded.decode(errors="replace")
  return recorded == attrs_digest(obj.attrs)


# ------------------------------------------------------------------ write
def _chunks(name, shape):
  if name in ("measurement", "clean", "albedo"):
    return (1, shape[1], 1, shape[3])
  if name in ("intensity", "depth"):
    return (1,) + tuple(shape[1:])
  return None


def _write_sequence(f: h5py.File, spec: DatasetSpec, seq: dict) -> None:
  group = f.require_group("sequences")
  name = seq["name"]
  if name in group:
    del group[name]
  g = group.create_group(name)
  g.attrs["complete"] = False
  for key, arr in seq["arrays"].items():
    chunks = _chunks(key, arr.shape)
    kw = {}
    if chunks is not None and spec.compression is not None:
      kw = dict(compression=spec.compression, shuffle=True)
      if spec.compression == "gzip":
        kw["compression_opts"] = spec.compression_level
    # fletcher32: every chunk carries a checksum that HDF5 checks on each read.
    g.create_dataset(key, data=arr, chunks=chunks if chunks is not None else True, fletcher32=True, **kw)
  for key, value in seq["attrs"].items():
    g.attrs[key] = value
  g.attrs["complete"] = True
  _seal(g)
  f.flush()


def _version() -> str:
  try:
    from importlib.metadata import version
    return version("nlosjax")
  except Exception:  # noqa: BLE001 - not installed
    return "unknown"


def _init_file(f: h5py.File, spec: DatasetSpec) -> None:
  s = spec.setup
  a = f.attrs
  a["format"] = FORMAT_NAME
  a["format_version"] = FORMAT_VERSION
  a["generator_version"] = scenes.GENERATOR_VERSION
  a["nlosjax_version"] = _version()
  a["wall_size"] = s.wall_size
  a["grid"] = np.asarray(s.grid, np.int64)
  a["bin_width"] = s.bin_width
  a["num_bins"] = s.num_bins
  a["spec"] = json.dumps(spec.to_dict())
  a["seed"] = spec.seed
  a["background_depth"] = scenes.BACKGROUND_DEPTH
  a["complete"] = False
  a["created"] = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
  f.require_group("sequences")
  _seal(f)


def _partial_path(path: pathlib.Path) -> pathlib.Path:
  return path.with_name(path.name + ".partial")


#: What h5py raises for a damaged file (besides a failed lock or permission).
_DAMAGE = (OSError, KeyError, ValueError, RuntimeError)


def _open_partial(tmp: pathlib.Path, spec: DatasetSpec, overwrite: bool) -> h5py.File:
  """Open (resume) or create the temp file; drop half-written and damaged sequences.

  Tells the faults apart by the error's kind, never by its text: HDF5's file lock held by
  another process (h5py raises ``BlockingIOError``) stops with a line saying so; a file that
  may not be written (``PermissionError``) stops naming it; a file whose writer was killed
  (HDF5's "open for writing" flag still set, no lock held) has its finished sequences copied
  into a fresh file (:func:`_salvage`: the killed writer may have left metadata past the
  file's recorded end, which writing on in place would overwrite); any other file HDF5
  cannot open is the unreadable leftover of a crash, a full disk or a truncation, and is
  replaced (with a warning). In a file that opens, each kept sequence is read back whole
  (HDF5 checks every chunk's checksum) and one that does not read back is redone.
  """
  if not tmp.exists():
    return _create_partial(tmp, spec)
  try:
    try:
      f = h5py.File(tmp, "a")
    except (BlockingIOError, PermissionError):
      raise
    except OSError:
      if _unlocked(tmp) and _clear_write_flag(tmp):    # its writer was killed
        return _salvage(tmp, spec, overwrite)
      raise
  except BlockingIOError:
    raise ValueError(f"{tmp}: is locked: another process is writing this dataset (HDF5 file lock); "
                     "wait for it to finish, or stop it, then rerun") from None
  except PermissionError as e:
    raise files.FileFault(tmp, f"{tmp}: cannot be opened for writing ({e.strerror or e}); "
                               f"{files.what_to_do(e.errno)}", e.errno) from None
  except OSError as e:
    if isinstance(e, files.FileFault):
      raise
    return _start_over(tmp, spec, "unreadable leftover of an interrupted run", e)
  try:
    same = _resumable(f, spec)
    if same:
      try:
        with files.writing(tmp):
          reserve_space(f, tmp)             # a full disk: stop here, the file as it is
      except files.FileFault:
        f.close()
        raise
      _drop_unfinished(f, tmp)
      return f
  except files.FileFault:
    raise
  except _DAMAGE as e:                 # damaged inside: start over
    with contextlib.suppress(Exception):
      f.close()
    return _start_over(tmp, spec, "damaged leftover of an interrupted run", e)
  f.close()
  return _other_configuration(tmp, spec, overwrite)


def _start_over(tmp: pathlib.Path, spec: DatasetSpec, what: str, error) -> h5py.File:
  warnings.warn(f"{tmp}: {what} ({' '.join(str(error).split())}); starting over", stacklevel=3)
  with files.writing(tmp):
    tmp.unlink()
  return _create_partial(tmp, spec)


def _other_configuration(tmp: pathlib.Path, spec: DatasetSpec, overwrite: bool) -> h5py.File:
  if not overwrite:
    raise ValueError(f"{tmp}: a leftover partial dataset made with another configuration or"
                     " generator version; pass overwrite=True (--overwrite) to replace it")
  with files.writing(tmp):
    tmp.unlink()
  return _create_partial(tmp, spec)


def _resumable(f: h5py.File, spec: DatasetSpec) -> bool:
  """Whether a leftover partial file is this spec's (ValueError where it is damaged or unsealed)."""
  if _attrs_intact(f) is False:
    raise ValueError("its attributes do not match the digest written with them")
  if f.attrs.get("format") != FORMAT_NAME or _generation_key(f.attrs.get("spec")) is None:
    raise ValueError("it records no readable spec (killed before its first flush?)")
  return (f.attrs.get("generator_version") == scenes.GENERATOR_VERSION
          and _generation_key(f.attrs.get("spec")) == spec.generation_key())


def _salvage(tmp: pathlib.Path, spec: DatasetSpec, overwrite: bool) -> h5py.File:
  """Copy the finished sequences of a killed writer's file that read back whole into a fresh one.

  The fresh file replaces ``tmp`` and is returned open for appending. A file too damaged to
  read is started over; another configuration's is refused as :func:`_open_partial` refuses it.
  """
  fresh = tmp.with_name(tmp.name + ".salvage")
  kept = 0
  try:
    with h5py.File(tmp, "r") as old:
      if not _resumable(old, spec):
        same = False
      else:
        same = True
        sealed = ATTRS_DIGEST in list(old.attrs)
        f = _create_partial(fresh, spec)
        try:
          for name in sorted(old["sequences"]):
            group = old["sequences"][name]
            why = _sequence_problem(group, sealed)
            if why is not None:
              if why != "half written":
                warnings.warn(f"{tmp}: sequence {name} is redone: {why}", stacklevel=3)
              continue
            with files.writing(fresh):
              reserve_space(f, fresh, sum(group[k].id.get_storage_size() for k in group))
            old.copy(group, f["sequences"], name=name)
            f.flush()
            kept += 1
        finally:
          f.close()
  except files.FileFault:
    fresh.unlink(missing_ok=True)
    raise
  except _DAMAGE as e:
    fresh.unlink(missing_ok=True)
    return _start_over(tmp, spec, "damaged leftover of a killed run", e)
  if not same:
    return _other_configuration(tmp, spec, overwrite)
  with files.writing(tmp):
    os.replace(fresh, tmp)
  f = h5py.File(tmp, "a")
  try:
    with files.writing(tmp):
      reserve_space(f, tmp)
  except files.FileFault:
    f.close()
    raise
  return f


def _create_partial(tmp: pathlib.Path, spec: DatasetSpec) -> h5py.File:
  with files.writing(tmp):
    try:
      f = h5py.File(tmp, "w", libver=LIBVER)
    except RuntimeError as e:          # HDF5's first writes failed (a full disk): its message has the errno
      if files.fault_errno(e) is None:
        raise
      raise files.FileFault(tmp, files.describe(e, tmp), files.fault_errno(e)) from e
    try:
      reserve_space(f, tmp)
    except OSError:
      f.close()
      raise
    _init_file(f, spec)
  return f


def _sequence_problem(group, sealed: bool) -> str | None:
  """Why a sequence of a leftover partial file is redone, or None to keep it."""
  if not group.attrs.get("complete", False):
    return "half written"
  if _attrs_intact(group) is False or (sealed and _attrs_intact(group) is None):
    return "its attributes do not match their digest"
  try:
    for key in group:
      group[key][()]                   # every chunk read: HDF5 checks its checksum
  except _DAMAGE as e:
    return f"it does not read back ({' '.join(str(e).split())})"
  return None


def _drop_unfinished(f: h5py.File, tmp: pathlib.Path) -> None:
  """Delete the sequences of a resumed file that are half written or do not read back intact."""
  sealed = ATTRS_DIGEST in list(f.attrs)     # written by a version that seals its sequences
  group = f["sequences"]
  for name in list(group):
    why = _sequence_problem(group[name], sealed)
    if why is not None:
      if why != "half written":
        warnings.warn(f"{tmp}: sequence {name} is redone: {why}", stacklevel=3)
      del group[name]


def _generation_key(spec_json):
  try:
    d = json.loads(spec_json)
    d.pop("num_sequences", None)
    return d
  except (TypeError, ValueError):
    return None


def _differences(stored: dict | None, wanted: dict, version) -> str:
  """What differs between a file's generation key (and generator version) and the config's, for errors."""
  if stored is None:
    return "the file records no readable spec"
  keys = sorted(k for k in set(stored) | set(wanted) if stored.get(k) != wanted.get(k))
  parts = [f"{k}: file {stored.get(k)!r}, config {wanted.get(k)!r}" for k in keys[:4]]
  if len(keys) > 4:
    parts.append(f"and {len(keys) - 4} more")
  if version != scenes.GENERATOR_VERSION:
    parts.append(f"generator version: file {version!r}, this code {scenes.GENERATOR_VERSION!r}")
  return "; ".join(parts) or "no difference found"


def _simulate_job(spec_dict, split, index):
  """Worker entry point (process pools pickle a plain dict, not the Setup)."""
  return simulate_sequence(DatasetSpec.from_config(spec_dict), split, index)


def _worker_threads(threads: int) -> None:
  """Worker initializer: limit XLA:CPU to ``threads`` threads before the worker computes anything.

  One JAX process already spreads its work over every core; ``W`` worker
  processes that each did so would share the cores ``W`` ways and gain
  nothing. With one thread per worker the processes run side by side.
  """
  if threads == 1:
    flags = os.environ.get("XLA_FLAGS", "")
    os.environ["XLA_FLAGS"] = (flags + " --xla_cpu_multi_thread_eigen=false"
                               " intra_op_parallelism_threads=1").strip()


@dataclasses.dataclass(frozen=True)
class WriteResult:
  """What :func:`write_dataset` did: the file, sequences simulated now, sequences kept."""

  path: pathlib.Path
  generated: int
  resumed: int


def write_dataset(path, spec: DatasetSpec, *, overwrite: bool = False, workers: int = 1,
                  progress: bool = True) -> WriteResult:
  """Simulate every sequence of ``spec`` into the HDF5 file ``path``.

  Crash safety: the data go to ``<path>.partial`` first, flushed after each
  sequence, and the file is renamed to ``path`` only when complete, so an
  existing ``path`` survives a crash. A rerun after a crash resumes the
  partial file: finished sequences are kept, a half-written one is redone.

  Args:
    path: output file.
    spec: the :class:`DatasetSpec`.
    overwrite: replace an existing ``path`` (and a leftover partial file of
      another configuration); without it an existing ``path`` raises.
    workers: processes simulating sequences in parallel (``1``: in this
      process; more use ``spawn``ed processes; the writing stays here). Where
      workers outnumber half the cores, each runs XLA on one thread
      (:func:`_worker_threads`): one process already uses every core.
    progress: show a tqdm progress bar.
  Returns:
    :class:`WriteResult` (``path``, sequences ``generated`` in this call,
    sequences ``resumed`` from a partial file).
  Raises:
    FileExistsError: ``path`` exists and ``overwrite`` is false.
    ValueError: bad arguments, or a partial file that cannot be resumed.
  """
  if not isinstance(spec, DatasetSpec):
    raise ValueError(f"spec must be a DatasetSpec, got {type(spec).__name__}")
  if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
    raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
  path = pathlib.Path(path)
  if path.exists() and not overwrite:
    raise FileExistsError(f"{path}: exists; pass overwrite=True (--overwrite) to replace it")
  if path.is_dir():
    raise ValueError(f"path {path} is a directory")
  tmp = _partial_path(path)
  with files.writing(path.parent):
    path.parent.mkdir(parents=True, exist_ok=True)
  f = _open_partial(tmp, spec, overwrite)
  try:
    done = set(f["sequences"])
    jobs = [(split, i) for split in SPLITS for i in range(spec.count(split))
            if sequence_name(split, i) not in done]
    from tqdm.auto import tqdm
    total = spec.num_sequences
    bar = tqdm(total=total, initial=total - len(jobs), unit="seq", desc=f"writing {path.name}",
               disable=not progress)
    if workers == 1 or len(jobs) <= 1:
      for split, i in jobs:
        seq = simulate_sequence(spec, split, i)
        reserve_space(f, tmp, sum(a.nbytes for a in seq["arrays"].values()))
        _write_sequence(f, spec, seq)
        bar.update()
    else:
      ctx = multiprocessing.get_context("spawn")
      spec_dict = spec.to_dict()
      threads = max(1, (os.cpu_count() or 1) // int(workers))
      with concurrent.futures.ProcessPoolExecutor(max_workers=int(workers), mp_context=ctx,
                                                  initializer=_worker_threads,
                                                  initargs=(threads,)) as pool:
        pending = set()
        queue_ = list(jobs)
        while queue_ or pending:
          while queue_ and len(pending) < 2 * workers:
            pending.add(pool.submit(_simulate_job, spec_dict, *queue_.pop(0)))
          finished, pending = concurrent.futures.wait(
              pending, return_when=concurrent.futures.FIRST_COMPLETED)
          for fut in finished:
            seq = fut.result()
            reserve_space(f, tmp, sum(a.nbytes for a in seq["arrays"].values()))
            _write_sequence(f, spec, seq)
            bar.update()
    bar.close()
    reserve_space(f, tmp)
    f.attrs["num_train"] = spec.num_train
    f.attrs["num_test"] = spec.num_test
    f.attrs["num_val"] = spec.num_val
    f.attrs["spec"] = json.dumps(spec.to_dict())    # the counts of a resumed or extended file
    f.attrs["complete"] = True
    _seal(f)
    f.close()                          # flushes: an error here leaves the partial file unrenamed
  except BaseException as e:
    with contextlib.suppress(Exception):
      f.close()
    if isinstance(e, OSError):         # a full disk, a folder made read-only: name the file
      raise files.FileFault(tmp, files.describe(e, tmp), files.fault_errno(e)) from e
    raise
  with files.writing(path):
    trim_reserved(tmp)
    os.replace(tmp, path)
  return WriteResult(path=path, generated=len(jobs), resumed=len(done))


def extend_dataset(path, spec: DatasetSpec, *, workers: int = 1, progress: bool = True) -> WriteResult:
  """Add to the complete file ``path`` the sequences ``spec`` has and it lacks.

  For a file made before a split existed (e.g. ``val``) or with fewer
  sequences: the stored sequences are kept byte for byte (a sequence depends
  on its seed, not on the counts), the missing ones are simulated, and the
  file is replaced atomically as :func:`write_dataset` does (the original
  stays untouched until the extended file is complete).

  Returns:
    :class:`WriteResult` (``generated`` 0 when nothing was missing).
  Raises:
    ValueError: ``path`` was made with another generation configuration, or
      holds more sequences of a split than ``spec`` asks for.
  """
  path = pathlib.Path(path)
  with _open_read(path) as f:
    if not bool(f.attrs.get("complete", False)) or _attrs_intact(f) is False:
      open_dataset(path).close()       # raises, naming what is wrong
    stored, wanted = _generation_key(f.attrs.get("spec")), spec.generation_key()
    if stored != wanted or f.attrs.get("generator_version") != scenes.GENERATOR_VERSION:
      raise ValueError(f"{path}: made with another data configuration or generator version "
                       f"({_differences(stored, wanted, f.attrs.get('generator_version'))}); "
                       "move it away (or point data.path elsewhere) to generate this one")
    have = {split: sum(1 for n in f["sequences"] if n.startswith(split + "-")) for split in SPLITS}
  more = {s: have[s] for s in SPLITS if have[s] > spec.count(s)}
  if more:
    raise ValueError(f"{path}: holds more sequences than the config asks for ({more}); "
                     "use a config with at least these counts")
  if all(have[s] == spec.count(s) for s in SPLITS):
    return WriteResult(path=path, generated=0, resumed=sum(have.values()))
  tmp = _partial_path(path)
  if not tmp.exists():
    with files.replaced(tmp) as copy:      # whole, or not at all (a full disk)
      shutil.copyfile(path, copy)
  return write_dataset(path, spec, overwrite=True, workers=workers, progress=progress)


# ------------------------------------------------------------------- read
#: What to do about a dataset file that does not read (the messages of :func:`_open_read` and the reader).
REGENERATE = "move it away (or delete it) and rerun: the dataset is made again from its spec"


def _unreadable(path, error) -> ValueError:
  return ValueError(f"{path}: cannot be read as HDF5 (truncated, corrupt or not an HDF5 file:"
                    f" {' '.join(str(error).split())}); {REGENERATE}")


@contextlib.contextmanager
def _open_read(path):
  """``h5py.File(path, "r")``; a file HDF5 cannot open or read raises ValueError naming it."""
  try:
    f = h5py.File(path, "r")
  except FileNotFoundError:
    raise FileNotFoundError(f"{path}: no such dataset file") from None
  except OSError as e:
    raise _unreadable(path, e) from None
  try:
    yield f
  except (OSError, KeyError, RuntimeError) as e:    # a chunk whose checksum fails, a damaged object
    raise ValueError(f"{path}: reading it failed (the file is damaged: {' '.join(str(e).split())});"
                     f" {REGENERATE}") from None
  finally:
    f.close()


class DynamicDataset:
  """Read access to a dataset file written by :func:`write_dataset`.

  Args:
    path: the HDF5 file.
    setup: optional expected full-resolution :class:`Setup` (e.g. the
      model's); a mismatch raises.

  Raises:
    FileNotFoundError: ``path`` does not exist.
    ValueError: naming the file, when it is not HDF5 (truncated or
      foreign), not an nlosjax dynamic dataset, of a newer format version,
      unfinished, or its Setup differs from ``setup``.
  """

  def __init__(self, path, setup: Setup | None = None):
    self.path = pathlib.Path(path)
    if not self.path.exists():
      raise FileNotFoundError(f"{self.path}: no such dataset file")
    try:
      self._file = h5py.File(self.path, "r")
    except OSError as e:
      raise _unreadable(self.path, e) from None
    try:
      with self._damage("opening it"):
        self._check()
      if setup is not None:
        self.check_setup(setup)
    except BaseException:
      self._file.close()
      raise

  @contextlib.contextmanager
  def _damage(self, what: str):
    """HDF5's errors of a damaged file (a failed checksum, an object that does not open) as one ValueError."""
    try:
      yield
    except (OSError, KeyError, RuntimeError) as e:
      raise ValueError(f"{self.path}: {what} failed (the file is damaged: {' '.join(str(e).split())});"
                       f" {REGENERATE}") from None

  def _check(self):
    a = self._file.attrs
    intact = _attrs_intact(self._file)
    fmt = a.get("format")
    if isinstance(fmt, bytes):
      fmt = fmt.decode()
    try:
      newer = fmt == FORMAT_NAME and int(a.get("format_version", -1)) > FORMAT_VERSION
    except (TypeError, ValueError):
      newer = False
    if intact is False and not newer:    # a newer version may seal otherwise: its version is the news
      raise ValueError(f"{self.path}: its attributes do not match the digest written with them (the"
                       f" file is damaged); {REGENERATE}")
    if fmt != FORMAT_NAME:
      raise ValueError(f"{self.path}: an HDF5 file but not an nlosjax dynamic NLOS dataset"
                       f" (attribute 'format' is {fmt!r}, expected {FORMAT_NAME!r})")
    version = int(a.get("format_version", -1))
    if version > FORMAT_VERSION or version < 1:
      raise ValueError(f"{self.path}: format_version {version} is not supported (this nlosjax"
                       f" reads versions 1..{FORMAT_VERSION}); update nlosjax")
    if not bool(a.get("complete", False)):
      raise ValueError(f"{self.path}: the dataset was not finished (interrupted writer?)")
    missing = [k for k in ("wall_size", "grid", "bin_width", "num_bins") if k not in a]
    if missing or "sequences" not in self._file:
      raise ValueError(f"{self.path}: malformed dataset; missing {missing or ['/sequences']}")
    try:
      self.setup = Setup(wall_size=float(a["wall_size"]), grid=tuple(int(v) for v in a["grid"]),
                         bin_width=float(a["bin_width"]), num_bins=int(a["num_bins"]))
    except ValueError as e:
      raise ValueError(f"{self.path}: invalid Setup attributes: {e}") from None
    self.attrs = dict(a)
    self._names = sorted(self._file["sequences"])
    damaged = [n for n in self._names if _attrs_intact(self._file["sequences"][n]) is False]
    if damaged:
      raise ValueError(f"{self.path}: the attributes of sequence(s) {', '.join(damaged[:3])} do not match"
                       f" the digest written with them (the file is damaged); {REGENERATE}")
    self._handles = {}

  # -- context manager
  def close(self):
    self._file.close()

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()

  @property
  def generator_version(self) -> str:
    return str(self.attrs.get("generator_version"))

  def check_setup(self, setup: Setup) -> None:
    """Raise ``ValueError`` naming the file if its Setup differs from ``setup``."""
    if not isinstance(setup, Setup):
      raise ValueError(f"setup must be a nlosjax.physics.Setup, got {type(setup).__name__}")
    mine, theirs = self.setup, setup.ungated()
    diffs = []
    for field in ("wall_size", "grid", "bin_width", "num_bins"):
      a, b = getattr(mine, field), getattr(theirs, field)
      same = a == b if field in ("grid", "num_bins") else math.isclose(a, b, rel_tol=1e-9)
      if not same:
        diffs.append(f"{field} {a!r} in the file vs {b!r} expected")
    if diffs:
      raise ValueError(f"{self.path}: dataset Setup does not match: " + "; ".join(diffs))

  def names(self, split: str | None = None) -> list[str]:
    """Sequence names (sorted), all or those of ``split``."""
    if split is None:
      return list(self._names)
    _check_split(split)
    with self._damage("reading the sequences' splits"):
      return [n for n in self._names if self._group(n).attrs.get("split") == split]

  def _group(self, name):
    if not isinstance(name, str) or name not in self._names:
      raise ValueError(f"{self.path}: no sequence {name!r}")
    with self._damage(f"opening sequence {name}"):
      return self._file["sequences"][name]

  def sequence_attrs(self, name: str) -> dict:
    """Attributes of sequence ``name`` (numpy scalars/arrays, strings)."""
    group = self._group(name)
    with self._damage(f"reading the attributes of {name}"):
      return dict(group.attrs)

  def has(self, name: str, key: str) -> bool:
    group = self._group(name)
    with self._damage(f"reading sequence {name}"):
      return key in group

  def num_frames(self, name: str) -> int:
    return int(self._dataset(name, "measurement").shape[0])

  def _dataset(self, name, key):
    ds = self._handles.get((name, key))
    if ds is None:
      with self._damage(f"opening {name}/{key}"):
        ds = self._handles[(name, key)] = self._open_dataset(name, key)
    return ds

  def _open_dataset(self, name, key):
    g = self._group(name)
    if key not in g:
      raise ValueError(f"{self.path}: sequence {name!r} has no dataset {key!r} (it has"
                       f" {sorted(g)})")
    ds = g[key]
    H, W = self.setup.grid
    T = self.setup.num_bins
    expected = {"measurement": (T, H, W), "clean": (T, H, W), "albedo": (T, H, W),
                "intensity": (H, W), "depth": (H, W), "trajectory": (3,)}.get(key)
    if expected is not None and tuple(ds.shape[1:]) != expected:
      raise ValueError(f"{self.path}: {name}/{key} has shape {ds.shape}, expected [F, "
                       f"{', '.join(map(str, expected))}] for the file's Setup")
    return ds

  def read(self, name: str, key: str, frames=slice(None), stride: int = 1, offset: int = 0,
           dtype=None) -> np.ndarray:
    """Read ``key`` of sequence ``name``.

    Args:
      name: sequence name (see :meth:`names`).
      key: one of :data:`DATASETS`.
      frames: an int, a slice, or a list of frame indices.
      stride, offset: under-scanning of the scan grid (not for ``trajectory``).
      dtype: cast to this dtype (default: as stored).
    Returns:
      numpy array, ``[F', ...]`` (``[...]`` for an int frame).
    """
    stride, offset = _check_stride(stride, offset)
    ds = self._dataset(name, key)
    if key == "trajectory" and stride != 1:
      raise ValueError("stride applies to scan-grid datasets, not 'trajectory'")
    index = frames
    if isinstance(frames, (int, np.integer)) and not isinstance(frames, bool):
      if not 0 <= frames < ds.shape[0]:
        raise ValueError(f"frames {frames} out of range [0, {ds.shape[0]}) of {name}/{key}")
      index = int(frames)
    elif not isinstance(frames, slice):
      index = np.asarray(frames, np.int64)
    try:
      if isinstance(index, np.ndarray):
        uniq, inverse = np.unique(index, return_inverse=True)
        if uniq.size and (uniq[0] < 0 or uniq[-1] >= ds.shape[0]):
          raise ValueError(f"frames {index.tolist()} out of range [0, {ds.shape[0]})")
        lo, hi = (int(uniq[0]), int(uniq[-1]) + 1) if uniq.size else (0, 0)
        out = self._read_grid(ds, slice(lo, hi), stride, offset)[uniq - lo][inverse]
      else:
        out = self._read_grid(ds, index, stride, offset)
    except (OSError, KeyError, RuntimeError) as e:
      raise ValueError(f"{self.path}: reading {name}/{key} failed (the file is damaged:"
                       f" {' '.join(str(e).split())}); {REGENERATE}") from None
    return out if dtype is None else out.astype(dtype)


  @staticmethod
  def _read_grid(ds, frames, stride, offset):
    """``ds[frames]`` under-scanned; transients are read one kept scan row at a time.

    HDF5 strided selections are slow (per-element bookkeeping); rows are
    whole chunks (``[1, T, 1, W]``), so reading the kept rows and slicing
    the columns in numpy is 5-20x faster and decompresses ``1 / stride`` of the data.
    """
    if ds.ndim < 3 or stride == 1:
      return ds[frames]
    if ds.ndim == 3:
      return ds[frames][..., offset::stride, offset::stride]
    rows = range(offset, ds.shape[2], stride)
    out = np.stack([ds[frames, :, r, :] for r in rows], axis=-2)
    return out[..., offset::stride]


def open_dataset(path, setup: Setup | None = None) -> DynamicDataset:
  """Open a dataset file for reading; see :class:`DynamicDataset`."""
  return DynamicDataset(path, setup)


def _array_names(f: h5py.File) -> list[str]:
  """Every array's path in an open file, sorted (the order both summaries read them in)."""
  names = []
  f.visititems(lambda name, obj: names.append(name) if isinstance(obj, h5py.Dataset) else None)
  return sorted(names)


def dataset_digest(path, *, chunk_bytes: int = 1 << 24) -> str:
  """SHA-256 (hex, 16 characters) of a dataset file's content: every array, by name, dtype, shape and value.

  Attributes and HDF5 layout (chunking, compression, timestamps) play no part, so
  two files written from the same spec on machines that compute the same values
  have the same digest, and a regenerated file can be checked against a recorded
  one (:mod:`nlosjax.train.run_state`). Reads the whole file once, ``chunk_bytes``
  at a time along each array's first axis.
  """
  h = hashlib.sha256()
  with _open_read(pathlib.Path(path)) as f:
    for name in _array_names(f):
      ds = f[name]
      h.update(f"{name}|{ds.dtype.str}|{ds.shape}\n".encode())
      if ds.shape == () or ds.size == 0:
        h.update(np.asarray(ds[()]).tobytes())
        continue
      row = max(1, ds.size // ds.shape[0] * ds.dtype.itemsize)
      step = max(1, chunk_bytes // row)
      for i in range(0, ds.shape[0], step):
        h.update(np.ascontiguousarray(ds[i:i + step]).tobytes())
  return h.hexdigest()[:16]


#: How far a regenerated file's :func:`dataset_fingerprint` may stand from a recorded one and still be
#: taken as the same data: each cell sum within this fraction of its array's L1 mass. Regenerating the
#: ``cpu`` preset's data at the tests' size with XLA:CPU's SSE4.2 code against its AVX-512/AVX2 code
#: moved cell sums by at most 2.1e-7 of that mass (a few noise-free values by float rounding); any
#: change of spec, seed or generator moves them by percent (``tests/test_data_fingerprint.py``).
FINGERPRINT_RTOL = 1e-4


def _cell_sums(x: np.ndarray, parts: int) -> list[float]:
  """Sums of ``x`` (float64) over a grid of ``min(parts, n)`` slabs per axis, in C order."""
  x = np.asarray(x, np.float64)
  if x.ndim == 0:
    return [float(x)]
  for axis in range(x.ndim):
    n = x.shape[axis]
    edges = np.linspace(0, n, min(parts, n) + 1).round().astype(int)[:-1] if n else np.zeros(1, int)
    x = np.add.reduceat(x, edges, axis=axis) if n else np.zeros(x.shape[:axis] + (1,) + x.shape[axis + 1:])
  return [float(v) for v in x.ravel()]


def _array_fingerprint(x: np.ndarray, parts: int) -> dict:
  """One array's entry of :func:`dataset_fingerprint`: shape, L1 mass, cell sums (float64)."""
  return {"shape": list(x.shape), "mass": float(np.abs(x, dtype=np.float64).sum()),
          "cells": _cell_sums(x, parts)}


def dataset_fingerprint(path, *, parts: int = 2) -> dict[str, dict]:
  """A dataset file's content summarised so that float rounding does not change it beyond tolerance.

  :func:`dataset_digest` names exact content, and XLA:CPU rounds differently on another CPU
  model (another vector width), so a file regenerated there from the same spec has another
  digest. This summary tells "the same data, rounded differently" from "other data": for each
  numeric array (each sequence's ``measurement``, ``clean``, ``intensity``, ...), its shape, its
  L1 mass ``sum |x|`` and its sums over ``parts`` slabs along every axis (16 cells for a
  ``[F, T, H, W]`` array), all in float64. Compare two with :func:`fingerprint_differences`.

  Returns:
    ``{array path: {"shape": [...], "mass": float, "cells": [float, ...]}}``, JSON-ready
    (about 20 numbers an array).
  """
  out = {}
  with _open_read(pathlib.Path(path)) as f:
    for name in _array_names(f):
      ds = f[name]
      if ds.dtype.kind not in "biuf":
        continue
      out[name] = _array_fingerprint(np.asarray(ds[()]), parts)
  return out


def _relative_difference(a: dict, b: dict) -> float:
  """The largest cell (or mass) difference of two fingerprints of one array over the larger L1 mass."""
  scale = max(float(a["mass"]), float(b["mass"]))
  diff = max([abs(float(x) - float(y)) for x, y in zip(a["cells"], b["cells"])]
             + [abs(float(a["mass"]) - float(b["mass"]))])
  return diff / scale if scale > 0 else (0.0 if diff == 0 else math.inf)


def fingerprint_differences(recorded: dict, current: dict, *, rtol: float = FINGERPRINT_RTOL) -> list[str]:
  """What tells ``current`` (a :func:`dataset_fingerprint`) from ``recorded`` beyond float rounding.

  An array missing or added, a shape that differs, or a cell sum that differs by more than
  ``rtol`` times the array's L1 mass (the larger of the two) is named, worst first (at most
  eight lines). An empty list: the same data up to rounding.
  """
  if not rtol >= 0:
    raise ValueError(f"rtol must be >= 0, got {rtol}")
  lines = [f"{name}: recorded, not in these data" for name in sorted(set(recorded) - set(current))]
  lines += [f"{name}: in these data, not recorded" for name in sorted(set(current) - set(recorded))]
  worst = []
  for name in sorted(set(recorded) & set(current)):
    a, b = recorded[name], current[name]
    if list(a["shape"]) != list(b["shape"]) or len(a["cells"]) != len(b["cells"]):
      lines.append(f"{name}: shape {list(a['shape'])} recorded, {list(b['shape'])} now")
    elif (rel := _relative_difference(a, b)) > rtol:
      worst.append((rel, f"{name}: cell sums differ by {rel:.3g} of its L1 mass (tolerance {rtol:g})"))
  lines += [text for _, text in sorted(worst, reverse=True)]
  return lines[:8] + ([f"... and {len(lines) - 8} more"] if len(lines) > 8 else [])


def _cache_checksum(entry: dict) -> str:
  """SHA-256 (16 hex characters) of a ``.digest.json`` entry without its checksum."""
  body = json.dumps({k: v for k, v in entry.items() if k != "checksum"}, sort_keys=True)
  return hashlib.sha256(body.encode()).hexdigest()[:16]


def dataset_identity(path, *, parts: int = 2, cache: bool = True) -> tuple[str, dict[str, dict]]:
  """``(dataset_digest(path), dataset_fingerprint(path))`` from one read of the file, cached beside it.

  Each array is read once, whole, and both summaries are taken from it (the digest is the same
  SHA-256 stream :func:`dataset_digest` hashes chunk by chunk). With ``cache``, the pair is kept in
  ``<file>.digest.json`` keyed by the file's size and modification time, so a run that resumes on
  an unchanged file pays nothing; a cache that cannot be written (a read-only folder) is skipped.
  """
  path = pathlib.Path(path)
  stat = path.stat()
  key = {"size": stat.st_size, "mtime_ns": stat.st_mtime_ns, "parts": parts}
  store = path.with_name(path.name + ".digest.json")
  if cache and store.exists():
    try:
      saved = json.loads(store.read_text())
    except (OSError, ValueError):
      saved = {}
    if (isinstance(saved, dict) and {k: saved.get(k, 2 if k == "parts" else None) for k in key} == key
        and isinstance(saved.get("digest"), str) and isinstance(saved.get("fingerprint"), dict)
        and saved.get("checksum", _cache_checksum(saved)) == _cache_checksum(saved)):   # a damaged cache: read again
      return saved["digest"], saved["fingerprint"]
  h = hashlib.sha256()
  fingerprint = {}
  with _open_read(path) as f:
    for name in _array_names(f):
      ds = f[name]
      x = np.asarray(ds[()])
      h.update(f"{name}|{ds.dtype.str}|{ds.shape}\n".encode())
      h.update(np.ascontiguousarray(x))     # its bytes in C order (no copy), as dataset_digest's chunks
      if ds.dtype.kind in "biuf":
        fingerprint[name] = _array_fingerprint(x, parts)
  digest = h.hexdigest()[:16]
  if cache:                      # written whole, then renamed: processes sharing the file never read half
    tmp = store.with_name(f"{store.name}.{os.getpid()}.tmp")
    try:
      entry = {**key, "digest": digest, "fingerprint": fingerprint}
      tmp.write_text(json.dumps({**entry, "checksum": _cache_checksum(entry)}) + "\n")
      os.replace(tmp, store)
    except OSError:
      tmp.unlink(missing_ok=True)
  return digest, fingerprint


def fingerprint_distance(recorded: dict, current: dict) -> float:
  """The largest cell difference over the arrays both fingerprints hold, relative to L1 mass (0: none)."""
  common = [n for n in set(recorded) & set(current) if len(recorded[n]["cells"]) == len(current[n]["cells"])]
  return max((_relative_difference(recorded[n], current[n]) for n in common), default=0.0)
