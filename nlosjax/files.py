"""Files a run writes, written so that a fault ends in a resume or in one clear error.

A long run writes many files (the dataset, checkpoints, the exported state, logs, results,
weights) on disks that fill up, folders that turn out read-only, and machines that die
mid-write. The rules every writer keeps (``docs/training.md``, "What survives what"):

* a file that a reader may find complete is replaced whole: written to a temporary file beside
  it and renamed over it (:func:`write_text_atomic`, :func:`write_bytes_atomic`,
  :func:`replaced`), so a kill or a full disk leaves the previous version, never half of one;
* an ``OSError`` of a write names the file, what went wrong and what to do
  (:class:`FileFault`, raised by :func:`writing`), instead of a bare ``[Errno 28]``.

Nothing here imports JAX.
"""

from __future__ import annotations

import contextlib
import errno as _errno
import os
import pathlib
import re

#: errnos of a disk that is full, or of a file past the process's size limit (``ulimit -f``).
DISK_FULL = frozenset({_errno.ENOSPC, _errno.EFBIG, _errno.EDQUOT})
#: errnos of a file or folder that may not be written.
NOT_WRITABLE = frozenset({_errno.EACCES, _errno.EPERM, _errno.EROFS})


class FileFault(OSError):
  """An ``OSError`` whose message names the file, what went wrong and what to do (one line).

  ``errno`` and ``filename`` are those of the fault (``errno`` may be None).
  """

  def __init__(self, path, message: str, errno: int | None = None):
    super().__init__(errno, message, str(path))
    self.message = message

  def __str__(self) -> str:
    return self.message


def fault_errno(error: BaseException) -> int | None:
  """The errno of an ``OSError``, also where h5py only writes it into its message (``errno = 28``)."""
  number = getattr(error, "errno", None)
  if isinstance(number, int):
    return number
  found = re.search(r"errno\s*=\s*(\d+)|os_error_code='?(\d+)", str(error))   # h5py's, TensorStore's
  return int(found.group(1) or found.group(2)) if found else None


def what_to_do(number: int | None) -> str:
  """What a user does about an ``OSError`` of errno ``number`` while a command writes."""
  if number in DISK_FULL:
    return ("the disk is full or a file-size limit (ulimit -f) was reached: free space (or raise "
            "the limit) and rerun the same command; it goes on from what was written")
  if number in NOT_WRITABLE:
    return ("the folder or file may not be written: make it writable, or point the command at a "
            "writable folder, and rerun")
  if number == _errno.ENOENT:
    return "check the path"
  return "check the disk and rerun the same command"


def describe(error: OSError, path=None) -> str:
  """One line for an ``OSError`` of writing ``path`` (default: the error's own ``filename``)."""
  if isinstance(error, FileFault):
    return str(error)
  number = fault_errno(error)
  where = path if path is not None else getattr(error, "filename", None)
  if number is None and where is None:          # an OSError raised with a message of its own
    return " ".join(str(error).split()) or type(error).__name__
  why = getattr(error, "strerror", None) or str(error) or type(error).__name__
  if number is not None and getattr(error, "strerror", None) is None:
    why = os.strerror(number)
  why = " ".join(why.split())
  return f"{where}: {why}; {what_to_do(number)}" if where else f"{why}; {what_to_do(number)}"


@contextlib.contextmanager
def writing(path):
  """Turn an ``OSError`` raised inside into a :class:`FileFault` naming ``path`` (one line)."""
  try:
    yield
  except FileFault:
    raise
  except OSError as e:
    raise FileFault(path, describe(e, path), fault_errno(e)) from e


def _temporary(path: pathlib.Path) -> pathlib.Path:
  """A hidden name beside ``path``, unique to this process, ending in ``path``'s suffix (writers read it)."""
  return path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")


@contextlib.contextmanager
def replaced(path):
  """Yield a temporary path beside ``path``; on success it is renamed over ``path``.

  What the block writes there replaces ``path`` whole, or, where the block raises (a full
  disk), not at all: the temporary file is removed and ``path`` keeps its previous content.
  An ``OSError`` comes out as a :class:`FileFault` naming ``path``.
  """
  path = pathlib.Path(path)
  tmp = _temporary(path)
  with writing(path):
    try:
      yield tmp
      os.replace(tmp, path)
    except BaseException:
      with contextlib.suppress(OSError):
        tmp.unlink()
      raise


def write_bytes_atomic(path, data: bytes) -> None:
  """Replace ``path`` with ``data`` whole (:func:`replaced`)."""
  with replaced(path) as tmp:
    tmp.write_bytes(data)


def write_text_atomic(path, text: str) -> None:
  """Replace ``path`` with ``text`` whole (:func:`replaced`)."""
  with replaced(path) as tmp:
    tmp.write_text(text)


def reserve(path, offset: int, nbytes: int) -> None:
  """Allocate ``[offset, offset + nbytes)`` of ``path`` on disk now, so a full disk fails here.

  HDF5 (2.0, as h5py 3.16 bundles it) crashes the process (a segmentation fault) when one of
  its writes fails, so writers of HDF5 files reserve the space a step will need before HDF5
  writes it: a full disk or a file-size limit is then an ``OSError`` raised here, before HDF5
  has written anything, and the file stays as the last step left it. Space already allocated
  is not allocated twice; HDF5 ignores what lies past its own end of file and trims it later.
  """
  fd = os.open(path, os.O_RDWR)
  try:
    os.posix_fallocate(fd, int(offset), max(int(nbytes), 1))
  finally:
    os.close(fd)


def probe_space(folder, nbytes: int) -> None:
  """Raise an ``OSError`` now where ``folder`` cannot take a file of ``nbytes`` (full, read-only, size limit).

  For writers whose own failures are hard to read (orbax's TensorStore errors, its background
  threads): a file of that size is allocated in ``folder`` and removed at once.
  """
  probe = pathlib.Path(folder) / f".space-probe-{os.getpid()}"
  fd = os.open(probe, os.O_CREAT | os.O_WRONLY | os.O_TRUNC, 0o600)
  try:
    os.posix_fallocate(fd, 0, max(int(nbytes), 1))
  finally:
    os.close(fd)
    with contextlib.suppress(OSError):
      probe.unlink()


#: The HDF5 attribute that holds a digest of its object's other attributes (:func:`attrs_digest`):
#: HDF5 keeps string attributes in its global heap, which no checksum covers.
ATTRS_DIGEST = "attrs_sha256"


def _canonical(value) -> bytes:
  """An HDF5 attribute value's bytes as h5py reads it back (str, bytes, numpy scalar or array)."""
  import numpy as np
  if isinstance(value, str):
    return b"s" + value.encode()
  if isinstance(value, bytes):
    return b"b" + value
  a = np.asarray(value)
  if a.dtype.kind == "O":
    return b"o" + repr(a.tolist()).encode()
  return a.dtype.str.encode() + repr(a.shape).encode() + a.tobytes()


def attrs_digest(attrs) -> str:
  """SHA-256 (16 hex characters) of an HDF5 object's attributes other than :data:`ATTRS_DIGEST`."""
  import hashlib
  h = hashlib.sha256()
  for key in sorted(k for k in attrs if k != ATTRS_DIGEST):
    h.update(key.encode() + b"\0" + _canonical(attrs[key]) + b"\0")
  return h.hexdigest()[:16]


def seal_attrs(obj) -> None:
  """Write the digest of an h5py object's attributes (:data:`ATTRS_DIGEST`), read back as a reader reads them."""
  obj.attrs[ATTRS_DIGEST] = attrs_digest(obj.attrs)


def attrs_intact(obj) -> bool | None:
  """Whether an h5py object's attributes match their digest (None: written without one).

  Listing the attributes raises where HDF5's own checksum of them fails.
  """
  if ATTRS_DIGEST not in list(obj.attrs):
    return None
  recorded = obj.attrs[ATTRS_DIGEST]
  if isinstance(recorded, bytes):
    recorded = recorded.decode(errors="replace")
  return recorded == attrs_digest(obj.attrs)


def one_line(message: str) -> str:
  """``message`` on one line: its lines stripped and joined with ``"; "`` (after a colon, a space)."""
  lines = [line.strip() for line in str(message).splitlines() if line.strip()]
  out = ""
  for line in lines:
    out += line if not out else (" " if out.endswith(":") else "; ") + line
  return out
