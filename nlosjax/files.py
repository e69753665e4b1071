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
  found = re.search(r"errno\s*=\s*(\d+)", str(error))
  return int(found.group(1)) if found else None


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


def one_line(message: str) -> str:
  """``message`` on one line: its lines stripped and joined with ``"; "`` (after a colon, a space)."""
  lines = [line.strip() for line in str(message).splitlines() if line.strip()]
  out = ""
  for line in lines:
    out += line if not out else (" " if out.endswith(":") else "; ") + line
  return out
