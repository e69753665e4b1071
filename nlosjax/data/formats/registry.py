"""The measurement-format registry and content-based format detection.

:data:`FORMATS` maps a format name to its :class:`FormatSpec` (reader,
container, summary, ``accepts`` check, options); each format module of
:mod:`nlosjax.data.formats` fills it with :func:`register_format` when
imported, and registration order is detection order.

Detection: the container (MATLAB v5 or HDF5, which includes MATLAB v7.3)
from the first bytes, then the first format whose ``accepts`` check passes
on the file's variables: ``rect_data`` or ``width`` -> ``lct_mat``, ``meas`` ->
``stanford_fk``, ``data`` or ``final_meas`` -> ``nlost_mat``, the root
attribute ``format`` -> the nlosjax layouts. A corrupt or unrecognised file
raises ``ValueError`` naming the file, the variables found and the
supported formats. The listing of a file's variables is cached per (file,
modification time, size).
"""

from __future__ import annotations

import dataclasses
import errno
import functools
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import scipy.io

from nlosjax import files
from nlosjax.physics.setup import Setup

# ----------------------------------------------------------------- registry

Reader = Callable[..., tuple[np.ndarray, Setup]]


@dataclasses.dataclass(frozen=True)
class FormatSpec:
  """One registered measurement format.

  Attributes:
    reader: ``reader(path, *, zero_bins, bin_factor, num_bins, **options)`` ->
      ``(counts [T, H, W] or [F, T, H, W], Setup)``; ``None`` arguments take
      the format's defaults; ``options`` are the names in :attr:`options`.
    container: file container(s) the format lives in, as :func:`detect_format`
      recognises them: ``"mat5"`` (MATLAB v5/v6/v7) or ``"hdf5"`` (HDF5, which
      includes MATLAB v7.3), or a tuple of both.
    summary: one line for error messages and docs.
    accepts: optional ``accepts(path) -> bool`` content check, used only to
      choose between several formats sharing one container.
    options: extra keyword options the reader takes (passed through from
      :func:`load_measurement`). A reader without ``"frame"`` returns a single
      capture ``[T, H, W]`` and :func:`load_measurement` handles ``frame``.
  """

  reader: Reader
  container: str | tuple[str, ...]
  summary: str
  accepts: Callable[[Path], bool] | None = None
  options: tuple[str, ...] = ()

  @property
  def containers(self) -> tuple[str, ...]:
    return (self.container,) if isinstance(self.container, str) else tuple(self.container)


#: format name -> :class:`FormatSpec`; filled by :func:`register_format`.
FORMATS: dict[str, FormatSpec] = {}

_CONTAINERS = ("mat5", "hdf5")


def register_format(name: str, reader: Reader, *, container: str | tuple[str, ...], summary: str,
                    accepts: Callable[[Path], bool] | None = None,
                    options: tuple[str, ...] = ()) -> None:
  """Add (or replace) the format ``name`` in :data:`FORMATS`.

  ``container`` is ``"mat5"``, ``"hdf5"`` or a tuple of them; ``options``
  names the reader's extra keyword options (see :class:`FormatSpec`).
  """
  containers = (container,) if isinstance(container, str) else tuple(container)
  if not containers or any(c not in _CONTAINERS for c in containers):
    raise ValueError(f"container must be one of {_CONTAINERS} (or a tuple of them), got {container!r}")
  FORMATS[name] = FormatSpec(reader=reader, container=container, summary=summary, accepts=accepts,
                             options=tuple(options))


def _supported() -> str:
  return "; ".join(f"{name!r}: {spec.summary}" for name, spec in FORMATS.items())


# ---------------------------------------------------------------- detection

_MAT5_MAGIC = b"MATLAB 5.0 MAT-file"   # text header of MATLAB v5, v6 and v7 files
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"     # HDF5 superblock signature
_HDF5_OFFSETS = (0, 512, 1024, 2048)   # where a superblock may sit (v7.3: 512)


def _container(path: Path) -> str | None:
  """``"mat5"``, ``"hdf5"`` or ``None`` from the file's first bytes."""
  with open(path, "rb") as f:
    head = f.read(_HDF5_OFFSETS[-1] + len(_HDF5_MAGIC))
  if head.startswith(_MAT5_MAGIC):
    return "mat5"
  if any(head[o:o + len(_HDF5_MAGIC)] == _HDF5_MAGIC for o in _HDF5_OFFSETS):
    return "hdf5"
  return None


def detect_format(path) -> str:
  """Name of the registered format that reads ``path``, from its content.

  The container comes from the first bytes: the MATLAB v5 text header
  ``'MATLAB 5.0 MAT-file'`` or the HDF5 signature ``'\\x89HDF\\r\\n\\x1a\\n'``
  (at byte 0, or 512 for MATLAB v7.3). Among the formats living in that
  container, the first (in registration order) whose ``accepts`` check passes
  on the variables or attributes in the file wins (a lone candidate needs no
  check). The file name is never consulted.

  Raises:
    FileNotFoundError: if ``path`` does not exist.
    ValueError: naming the file and the supported formats, when no registered
      format lives in the file's container, the container cannot be read
      (corrupt or truncated), or no format recognises the content.
  """
  path = _existing_file(path)
  container = _container(path)
  if container is None:
    raise ValueError(
        f"{path}: unrecognised file content (neither a MATLAB v5 .mat nor an HDF5 file)."
        f" Supported formats: {_supported()}")
  candidates = [name for name, spec in FORMATS.items() if container in spec.containers]
  if len(candidates) == 1:
    return candidates[0]
  kind = "an HDF5 file (MATLAB v7.3 or HDF5)" if container == "hdf5" else "a MATLAB v5 file"
  if candidates:
    _listing(path, container)    # a corrupt container raises here, naming the problem
  for name in candidates:
    accepts = FORMATS[name].accepts
    if accepts is None or accepts(path):
      return name
  held = ""
  if candidates:
    names = sorted(_variables(path)[1])
    held = f" holding {names}" if names else " holding no variable"
  raise ValueError(
      f"{path}: {kind}{held}, but no registered format reads it"
      f"{'' if candidates else ' (no reader for this container yet)'}."
      f" Supported formats: {_supported()}")


def _stat_key(path: Path) -> tuple:
  st = path.stat()
  return (str(path.resolve()), st.st_mtime_ns, st.st_size)


#: What to do about an input file that cannot be read (a measured capture, a dataset given by path).
DAMAGED_INPUT = "the file is damaged or cut short: copy it again from where it came from"


class _Unreadable(Exception):
  """A container that cannot be listed; the message completes ``"{path}: "``."""


@functools.lru_cache(maxsize=32)
def _listing_cached(key: tuple, container: str) -> dict:
  path = key[0]
  if container == "mat5":
    try:
      return {name: tuple(shape) for name, shape, _ in scipy.io.whosmat(path)}
    except MemoryError:
      raise
    except Exception as exc:
      raise _Unreadable(f"cannot be read as a MATLAB v5 file (corrupt, truncated or another"
                        f" format): {type(exc).__name__}: {exc}") from None
  try:
    with h5py.File(path, "r") as f:
      # An empty dataset (a null dataspace, as TAL writes an unset field) has no shape: listed as ().
      out = {name: (tuple(reversed(obj.shape or ())) if isinstance(obj, h5py.Dataset) else None)
             for name, obj in f.items()}
      out["#attrs"] = {k: _attr_value(v) for k, v in f.attrs.items()
                       if k in ("format", "format_version", "MATLAB_class")}
      intact = files.attrs_intact(f)     # nlosjax's files seal their attributes with a digest
  except MemoryError:
    raise
  except Exception as exc:
    raise _Unreadable(f"cannot be read as an HDF5 file (corrupt or truncated):"
                      f" {type(exc).__name__}: {exc}") from None
  if intact is False:
    raise _Unreadable("its attributes do not match the digest written with them (the file is damaged)")
  return out


def _listing(path: Path, container: str) -> dict:
  """``variable name -> shape`` (MATLAB axis order) of a ``.mat``/HDF5 file's top level.

  HDF5 groups map to ``None``, empty (null-dataspace) datasets to ``()``; the
  key ``"#attrs"`` of an HDF5 listing holds the root attributes ``format`` and
  ``format_version`` when present.
  Cached per (file, modification time, size).

  Raises:
    ValueError: naming the file when the container cannot be read.
  """
  try:
    out = dict(_listing_cached(_stat_key(path), container))
  except _Unreadable as exc:
    raise ValueError(f"{path}: {exc}; {DAMAGED_INPUT}") from None
  if container == "mat5":
    out.pop("#attrs", None)
  return out


def _variables(path: Path) -> tuple[str, dict]:
  """``(container, listing)`` of ``path``, without the attributes entry."""
  container = _container(path)
  if container is None:
    return None, {}
  listing = _listing(path, container)
  listing.pop("#attrs", None)
  return container, listing


def _root_format(path: Path) -> str | None:
  """The root ``format`` attribute of an HDF5 file (None if absent or not HDF5)."""
  if _container(path) != "hdf5":
    return None
  return _listing(path, "hdf5").get("#attrs", {}).get("format")


def _attr_value(value):
  if isinstance(value, bytes):
    return value.decode(errors="replace")
  if isinstance(value, np.ndarray) and value.dtype.kind in "SO" and value.size == 1:
    return _attr_value(value.ravel()[0])
  if isinstance(value, np.generic):
    return value.item()
  return value


def _existing_file(path) -> Path:
  path = Path(path)
  if not path.exists():
    raise FileNotFoundError(errno.ENOENT, f"measurement file not found: {path}", str(path))
  if not path.is_file():
    raise ValueError(f"{path}: not a regular file")
  return path
