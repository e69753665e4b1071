"""Loading for training: :class:`TripletLoader` (batches of frame triplets), :class:`LoaderOptions`
(how training reads a dataset) and :func:`prefetch`."""

from __future__ import annotations

import dataclasses
import queue
import threading
from collections.abc import Iterator, Mapping

import numpy as np

from nlosjax.data.dataset.file import DynamicDataset, open_dataset
from nlosjax.data.dataset.spec import _check_split
from nlosjax.data.dataset.undersampling import _check_stride, undersample
from nlosjax.physics.setup import Setup


def prefetch(iterator, size: int = 2) -> Iterator:
  """Run ``iterator`` in a background thread, ``size`` items ahead.

  The thread starts at the first item asked for. Exceptions in the producer are
  re-raised in the consumer; closing the returned generator stops the producer and
  waits for it (a generator never started has no thread to stop).
  """
  if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 1:
    raise ValueError(f"size must be an integer >= 1, got {size!r}")
  q: queue.Queue = queue.Queue(maxsize=int(size))
  stop = threading.Event()
  done = object()

  def put(item):
    while not stop.is_set():
      try:
        q.put(item, timeout=0.05)
        return True
      except queue.Full:
        continue
    return False

  def produce():
    try:
      for item in iterator:
        if not put((None, item)):
          return
      put((done, None))
    except BaseException as e:  # noqa: BLE001 - handed to the consumer
      put((e, None))

  thread = threading.Thread(target=produce, daemon=True, name="nlosjax-prefetch")

  def consume():
    thread.start()
    try:
      while True:
        tag, item = q.get()
        if tag is done:
          return
        if tag is not None:
          raise tag
        yield item
    finally:
      stop.set()
      thread.join()          # the producer ends within one item: nothing reads a file closed after this

  return consume()


@dataclasses.dataclass(frozen=True)
class LoaderOptions:
  """How training reads its dataset: a config's ``data.loader`` section, its one schema and reader.

  Attributes:
    ends: ``"valid"`` (middle frames with both neighbours) or ``"replicate"`` (every frame, the
      ends' missing neighbour replaced by the frame itself); :class:`TripletLoader`.
    target: ``"clean"`` (the noise-free transient) or ``"measurement"`` (the noisy counts).
    in_memory: read every sequence once, when the loader opens (else one read per batch).
    prefetch: batches read ahead in a background thread while the step runs (0: read in turn).
      Batches are a function of the step, so it changes no number; at the paper preset a batch
      read from disk takes about 0.3 s (``benchmarks/results/data.md``).
  """
  ends: str = "valid"
  target: str = "clean"
  in_memory: bool = True
  prefetch: int = 0

  def __post_init__(self):
    if self.ends not in ("valid", "replicate"):
      raise ValueError(f'data.loader.ends must be "valid" or "replicate", got {self.ends!r}')
    if self.target not in ("clean", "measurement"):
      raise ValueError(f'data.loader.target must be "clean" or "measurement", got {self.target!r}')
    if not isinstance(self.in_memory, (bool, np.bool_)):
      raise ValueError(f"data.loader.in_memory must be true or false, got {self.in_memory!r}")
    if isinstance(self.prefetch, bool) or not isinstance(self.prefetch, (int, np.integer)) or self.prefetch < 0:
      raise ValueError(f"data.loader.prefetch must be an integer >= 0, got {self.prefetch!r}")

  @classmethod
  def from_dict(cls, section: Mapping | None) -> "LoaderOptions":
    """The options of a ``data.loader`` mapping (None: the defaults); unknown keys are an error."""
    section = dict(section or {})
    names = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(section) - set(names))
    if unknown:
      raise ValueError(f"unknown data.loader key(s) {unknown}; known: {names}")
    return cls(**section)


class TripletLoader:
  """Batches of adjacent under-scanned frames (three by default) and the middle frame's targets.

  Args:
    dataset: a path or an open :class:`DynamicDataset`.
    split: ``"train"``, ``"test"`` or ``"val"``.
    batch_size: examples per batch ``B``.
    stride, offset: under-scanning of the input (:func:`undersample`).
    seed: shuffling seed.
    shuffle: permute examples every epoch (else file order: sequence, frame).
    drop_remainder: drop the last incomplete batch of an epoch.
    ends: ``"valid"`` or ``"replicate"`` (package docstring).
    target: ``"clean"`` (the noise-free transient; the file must store it)
      or ``"measurement"`` (the full-resolution noisy counts) for ``transient``.
    in_memory: read everything the loader needs once, at construction.
    setup: optional expected full-resolution Setup (checked).
    prefetch_size: default of :meth:`iterate`'s ``prefetch_size``.
    window: input frames per example, an odd number centred on the middle frame
      (3: the triplet); frame indices past a sequence's ends are clipped to it.
    shard: ``(index, count)``: :meth:`batch` returns rows ``index * B / count``
      to ``(index + 1) * B / count`` of every global batch and reads only
      those (one process of ``count`` in multi-process training; ``B`` must
      divide by ``count``). With ``in_memory`` a sharded loader keeps the
      sequences it has read instead of reading every one at construction.

  Batch (numpy, float32 unless noted): ``measurement [B, window, T, h, w]``,
  ``transient [B, T, H, W]``, ``intensity [B, H, W]``, ``depth [B, H, W]``
  (metres), ``sequence [B]`` int32 (index into :attr:`names`), ``frame
  [B]`` int32 (middle frame), ``efficiency [B]``.
  """

  def __init__(self, dataset, *, split: str = "train", batch_size: int = 4, stride: int = 1,
               offset: int = 0, seed: int = 0, shuffle: bool = True, drop_remainder: bool = True,
               ends: str = "valid", target: str = "clean", in_memory: bool = False,
               setup: Setup | None = None, prefetch_size: int = 0,
               shard: tuple[int, int] = (0, 1), window: int = 3):
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 1 or window % 2 == 0:
      raise ValueError(f"window must be a positive odd integer, got {window!r}")
    self.window = int(window)
    index, count = (int(v) for v in shard)
    if not (count >= 1 and 0 <= index < count):
      raise ValueError(f"shard must be (index, count) with 0 <= index < count, got {shard!r}")
    self.shard = (index, count)
    self._owns = not isinstance(dataset, DynamicDataset)
    self.dataset = open_dataset(dataset, setup) if self._owns else dataset
    if not self._owns and setup is not None:
      self.dataset.check_setup(setup)
    if isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) or batch_size < 1:
      raise ValueError(f"batch_size must be an integer >= 1, got {batch_size!r}")
    if ends not in ("valid", "replicate"):
      raise ValueError(f'ends must be "valid" or "replicate", got {ends!r}')
    if target not in ("clean", "measurement"):
      raise ValueError(f'target must be "clean" or "measurement", got {target!r}')
    self.stride, self.offset = _check_stride(stride, offset)
    self.split, self.batch_size, self.seed = _check_split(split), int(batch_size), int(seed)
    if self.batch_size % count:
      raise ValueError(f"batch_size {batch_size} does not split into {count} shards")
    self.shuffle, self.drop_remainder, self.ends, self.target = shuffle, drop_remainder, ends, target
    if (isinstance(prefetch_size, bool) or not isinstance(prefetch_size, (int, np.integer))
        or prefetch_size < 0):
      raise ValueError(f"prefetch_size must be an integer >= 0, got {prefetch_size!r}")
    self.prefetch_size = int(prefetch_size)
    self.names = self.dataset.names(split)
    if not self.names:
      raise ValueError(f"{self.dataset.path}: no {split!r} sequences")
    if target == "clean" and not self.dataset.has(self.names[0], "clean"):
      raise ValueError(f"{self.dataset.path}: stores no 'clean' transients; use"
                       " target='measurement' or regenerate with store_clean")
    self.setup = self.dataset.setup
    self.input_shape = undersample(np.empty((1, 1) + self.setup.grid), self.stride, self.offset).shape
    examples = []
    self._efficiency = []
    self._num_frames = []
    for s, name in enumerate(self.names):
      F = self.dataset.num_frames(name)
      self._num_frames.append(F)
      middles = range(1, F - 1) if ends == "valid" else range(F)
      examples += [(s, m) for m in middles]
      self._efficiency.append(float(self.dataset.sequence_attrs(name)["efficiency"]))
    if not examples:
      raise ValueError(f"{self.dataset.path}: {split!r} sequences are too short for triplets"
                       f" with ends={ends!r}")
    self.examples = np.asarray(examples, np.int64)
    self.steps_per_epoch = (len(examples) // self.batch_size if drop_remainder
                            else -(-len(examples) // self.batch_size))
    if self.steps_per_epoch == 0:
      raise ValueError(f"batch_size {batch_size} exceeds the {len(examples)} {split!r} examples"
                       " with drop_remainder=True")
    self._cache = None
    if in_memory:
      self._cache = ([self._load_sequence(name) for name in self.names] if count == 1
                     else [None] * len(self.names))

  def close(self):
    if self._owns:
      self.dataset.close()

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()

  def __len__(self):
    return self.steps_per_epoch

  def _load_sequence(self, name):
    ds = self.dataset
    return {"measurement": ds.read(name, "measurement", stride=self.stride, offset=self.offset),
            "transient": ds.read(name, self.target),
            "intensity": ds.read(name, "intensity"), "depth": ds.read(name, "depth")}

  def input_frames(self, middle: int, num_frames: int) -> np.ndarray:
    """``[window]`` input frame indices of the example with middle frame ``middle``, clipped to
    ``[0, num_frames)``."""
    half = self.window // 2
    return np.clip(np.arange(middle - half, middle + half + 1), 0, num_frames - 1)

  def order(self, epoch: int) -> np.ndarray:
    """Example indices in the order of ``epoch``."""
    n = len(self.examples)
    if not self.shuffle:
      return np.arange(n)
    return np.random.default_rng([self.seed, int(epoch)]).permutation(n)

  def batch(self, step: int) -> dict:
    """The batch of global step ``step`` (epoch ``step // len(self)``); deterministic.

    A sharded loader returns its rows of that batch (``shard``).
    """
    if isinstance(step, bool) or not isinstance(step, (int, np.integer)) or step < 0:
      raise ValueError(f"step must be an integer >= 0, got {step!r}")
    epoch, within = divmod(int(step), self.steps_per_epoch)
    idx = self.order(epoch)[within * self.batch_size:(within + 1) * self.batch_size]
    index, count = self.shard
    if count > 1:
      rows = len(idx) // count if self.drop_remainder else -(-len(idx) // count)
      idx = idx[index * rows:(index + 1) * rows]
    out = {k: [] for k in ("measurement", "transient", "intensity", "depth")}
    for s, m in self.examples[idx]:
      name = self.names[s]
      if self._cache is not None:
        if self._cache[s] is None:
          self._cache[s] = self._load_sequence(name)
        seq = self._cache[s]
        frames = self.input_frames(m, seq["measurement"].shape[0])
        out["measurement"].append(seq["measurement"][frames])
        for k in ("transient", "intensity", "depth"):
          out[k].append(seq[k][m])
      else:
        frames = self.input_frames(m, self._num_frames[s])
        out["measurement"].append(self.dataset.read(name, "measurement", frames, self.stride,
                                                    self.offset))
        out["transient"].append(self.dataset.read(name, self.target, int(m)))
        out["intensity"].append(self.dataset.read(name, "intensity", int(m)))
        out["depth"].append(self.dataset.read(name, "depth", int(m)))
    batch = {k: np.stack(v).astype(np.float32) for k, v in out.items()}
    batch["sequence"] = self.examples[idx, 0].astype(np.int32)
    batch["frame"] = self.examples[idx, 1].astype(np.int32)
    batch["efficiency"] = np.asarray([self._efficiency[s] for s in self.examples[idx, 0]], np.float32)
    return batch

  def iterate(self, start_step: int = 0, num_steps: int | None = None,
              prefetch_size: int | None = None) -> Iterator[dict]:
    """Yield ``batch(start_step)``, ``batch(start_step + 1)``, ... (forever if ``num_steps`` is None).

    Resume from a checkpointed step ``k`` with ``iterate(k)``. With
    ``prefetch_size > 0`` (default: the constructor's) batches are read that
    many ahead in a background thread.
    """
    if prefetch_size is None:
      prefetch_size = self.prefetch_size
    if isinstance(start_step, bool) or not isinstance(start_step, (int, np.integer)) or start_step < 0:
      raise ValueError(f"start_step must be an integer >= 0, got {start_step!r}")
    if num_steps is not None and (not isinstance(num_steps, (int, np.integer)) or num_steps < 0):
      raise ValueError(f"num_steps must be None or an integer >= 0, got {num_steps!r}")

    def gen():
      step = int(start_step)
      while num_steps is None or step < start_step + num_steps:
        yield self.batch(step)
        step += 1

    if prefetch_size:
      return prefetch(gen(), prefetch_size)
    return gen()

  def epoch(self, epoch: int, prefetch_size: int | None = None) -> Iterator[dict]:
    """The batches of one epoch."""
    return self.iterate(int(epoch) * self.steps_per_epoch, self.steps_per_epoch, prefetch_size)
