"""When a training run stops: after a fixed step count (the default), or when validation stops improving.

A config's ``train.stop`` section (:class:`StopRule`) picks the rule:

* ``{"rule": "steps"}`` (the default): ``train.steps`` steps, as before this
  module existed; nothing is validated during training (``train.select_checkpoint``
  still chooses among the kept checkpoints afterwards).
* ``{"rule": "plateau", "every": 50, "patience": 4, "min_delta_db": 0.05,
  "max_steps": 3000}``: the validation score ``metric`` (the ``validate`` callback
  of :func:`nlosjax.train.train_model`, dB: the intensity PSNR, or the
  object-balanced PSNR, :data:`METRICS`) is measured every ``every`` steps
  and at ``max_steps``; training stops at the first validation after which
  the best of the last ``patience`` validations is not more than
  ``min_delta_db`` above the best of all earlier ones (:func:`plateau_reached`),
  or at ``max_steps``. The model kept is the best on validation (the earliest
  of equal scores). ``train.steps`` is ignored.

**Learning-rate schedule under the plateau rule.** The run length is unknown
when training starts, but the schedule needs a horizon: it is ``max_steps``.
The configured schedule (``train.optim``: warm-up, cosine decay to
``end_fraction`` of the peak) is laid over ``max_steps`` steps, so a plateau
run is exactly the first steps of the fixed-length run ``{"rule": "steps"}``
with ``train.steps = max_steps`` (same parameters step by step), stopped
early. The stopping point therefore never changes the schedule the model saw
before it, and a resumed run cannot disagree with an uninterrupted one. The
price: a run that stops at step ``s`` has seen only the start of the decay
(the cosine's learning rate at ``s`` is in each curve point's ``lr``), so its
plateau is a plateau at that learning rate; a run meant to end with a fully
decayed rate has to reach ``max_steps``. Warm-up then constant would make the
plateau independent of ``max_steps`` but would drop the decay the presets
were tuned with.

Everything a resume needs is on disk in the model folder: the regular
checkpoints, ``best_checkpoint/`` (the best state so far), and
``validation_curve.json`` (one point per validation: step, the intensity PSNR, every
other score the callback returned and the deciding one, wall time, learning rate).
The rule is a pure function of the curve, so a resumed run
restores its patience state by reading the curve, and a finished run (whose
curve already says stop) trains nothing.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import pathlib
import time
from typing import Any, Callable, Sequence

RULES = ("steps", "plateau")
#: Validation scores a rule can stop and choose on (dB, higher is better): the whole-image intensity
#: PSNR (the default, which an image dark everywhere scores well on) and the object-balanced PSNR
#: (:func:`nlosjax.metrics.psnr_balanced`: object and background pixels weigh half each).
METRICS = ("psnr", "psnr_balanced")
CURVE_FILE = "validation_curve.json"
BEST_FOLDER = "best_checkpoint"


@dataclasses.dataclass(frozen=True)
class StopRule:
  """When training stops (module docstring); ``train.stop`` of a config.

  Attributes:
    rule: ``"steps"`` (``train.steps`` steps; the default) or ``"plateau"``.
    every: validate every this many steps (plateau).
    patience: validations without an improvement before stopping (plateau).
    min_delta_db: an improvement must exceed this many dB to count (plateau).
    max_steps: the longest run and the learning-rate schedule's horizon (plateau).
    metric: the validation score the plateau rule and ``train.select_checkpoint = "val"``
      decide on (:data:`METRICS`).
  """

  rule: str = "steps"
  every: int = 50
  patience: int = 4
  min_delta_db: float = 0.05
  max_steps: int = 3000
  metric: str = "psnr"

  def __post_init__(self):
    if self.rule not in RULES:
      raise ValueError(f"train.stop.rule must be one of {RULES}, got {self.rule!r}")
    if self.metric not in METRICS:
      raise ValueError(f"train.stop.metric must be one of {METRICS}, got {self.metric!r}")
    for name in ("every", "patience", "max_steps"):
      v = getattr(self, name)
      if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise ValueError(f"train.stop.{name} must be a positive integer, got {v!r}")
    if not (isinstance(self.min_delta_db, (int, float)) and self.min_delta_db >= 0):
      raise ValueError(f"train.stop.min_delta_db must be >= 0, got {self.min_delta_db!r}")

  @classmethod
  def from_config(cls, stop: dict | None) -> "StopRule":
    """The rule of a ``train.stop`` dict (None or ``{}``: the default ``"steps"``); unknown keys raise."""
    stop = dict(stop or {})
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = set(stop) - known
    if unknown:
      raise ValueError(f"train.stop: unknown key(s) {sorted(unknown)}; known: {sorted(known)}")
    return cls(**stop)

  def to_dict(self) -> dict:
    """The rule's fields; ``metric`` only where it is not the PSNR (curves and runs recorded before it
    existed compare equal)."""
    d = dataclasses.asdict(self)
    if d["metric"] == "psnr":
      d.pop("metric")
    return d

  def score(self, value) -> tuple[float, dict]:
    """``(deciding score, every score)`` of a ``validate`` callback's return: a float (the
    intensity PSNR) or a dict of scores (:func:`nlosjax.evaluation.protocol.validation_scores`)."""
    if isinstance(value, dict):
      scores = {k: float(v) for k, v in value.items()}
      if self.metric not in scores:
        raise ValueError(f"train.stop.metric {self.metric!r}: the validation callback returned only "
                         f"{sorted(scores)}")
      return scores[self.metric], scores
    if self.metric != "psnr":
      raise ValueError(f"train.stop.metric {self.metric!r} needs a validation callback returning a dict of "
                       "scores (nlosjax.evaluation.protocol.validation_scores), got a single number")
    return float(value), {"psnr": float(value)}

  def horizon(self, steps: int) -> int:
    """The run's last possible step and the schedule's horizon: ``steps`` or ``max_steps``."""
    return int(steps) if self.rule == "steps" else self.max_steps

  def validates_at(self, step: int) -> bool:
    """Whether the plateau rule validates after ``step`` steps (every ``every``, and at ``max_steps``)."""
    return self.rule == "plateau" and step > 0 and (step % self.every == 0 or step == self.max_steps)


def _finite(scores: Sequence[float]) -> list[float]:
  """Scores with NaN as -inf (a NaN validation never counts as the best)."""
  return [float(s) if not math.isnan(float(s)) else -math.inf for s in scores]


def plateau_reached(scores: Sequence[float], patience: int, min_delta_db: float) -> bool:
  """Whether validation has stopped improving: the plateau rule on a sequence of scores.

  Args:
    scores: validation PSNRs (dB) in the order measured, ``[n]``.
    patience: how many of the latest scores may fail to improve.
    min_delta_db: the margin an improvement must exceed, dB.
  Returns:
    True when ``n > patience`` and ``max(scores[-patience:]) <= max(scores[:-patience])
    + min_delta_db``: none of the last ``patience`` validations beat the best before
    them by more than ``min_delta_db``. NaN scores count as -inf.
  """
  s = _finite(scores)
  if len(s) <= patience:
    return False
  return max(s[-patience:]) <= max(s[:-patience]) + min_delta_db


def best_index(scores: Sequence[float]) -> int:
  """Index of the best score (the earliest of equal ones; NaN counts as -inf). ``scores`` non-empty."""
  s = _finite(scores)
  return max(range(len(s)), key=lambda i: (s[i], -i))


def stop_reason(rule: StopRule, scores: Sequence[float], steps_done: int) -> str | None:
  """Why a plateau run stops after ``steps_done`` steps with validation ``scores``, or None to go on.

  ``"plateau"`` (:func:`plateau_reached`) takes precedence over ``"max_steps"``
  (``steps_done >= rule.max_steps``). Always None for the ``"steps"`` rule (the loop's range ends it).
  """
  if rule.rule != "plateau":
    return None
  if plateau_reached(scores, rule.patience, rule.min_delta_db):
    return "plateau"
  if steps_done >= rule.max_steps:
    return "max_steps"
  return None


def simulate(rule: StopRule, score_at: Callable[[int], float]) -> tuple[int, str, list[int]]:
  """Where the plateau rule stops given ``score_at(step)``: ``(steps taken, reason, validated steps)``.

  The loop's decisions without any training: validate at each step the rule
  validates at, stop as :func:`stop_reason` says. For tests and for reading a
  curve measured at a finer spacing.
  """
  if rule.rule != "plateau":
    raise ValueError("simulate needs the plateau rule")
  steps, scores = [], []
  for step in range(1, rule.max_steps + 1):
    if not rule.validates_at(step):
      continue
    steps.append(step)
    scores.append(score_at(step))
    reason = stop_reason(rule, scores, step)
    if reason:
      return step, reason, steps
  raise AssertionError("unreachable: max_steps always stops")


def _write_json(path: pathlib.Path, obj) -> None:
  """Write ``obj`` as JSON to ``path`` atomically (a temporary file renamed over it)."""
  tmp = path.with_name(path.name + ".tmp")
  tmp.write_text(json.dumps(obj, indent=1) + "\n")
  os.replace(tmp, path)


def read_curve(folder) -> dict | None:
  """A model folder's ``validation_curve.json`` (written under the plateau rule), or None.

  ``{"rule": StopRule dict, "curve": [{"step", "val_psnr" (dB), "time_s", "val_s", "lr"}],
  "best_step", "best_val_psnr", "steps_taken", "stop_reason" (None while running)}``;
  ``time_s`` is the wall time of training and validation up to that point (summed over
  resumes; the work a kill lost is not counted), ``val_s`` what that validation took.
  """
  path = pathlib.Path(folder) / CURVE_FILE
  return json.loads(path.read_text()) if path.exists() else None


class PlateauTracker:
  """The plateau rule's state in one model folder: the validation curve and the best checkpoint.

  Order of every validation at step ``s`` (:meth:`record`): validate; the caller
  has already saved (and finished) the regular checkpoint of ``s``; the best
  state is saved to ``best_checkpoint/`` if ``s`` is a new best; last,
  ``validation_curve.json`` is replaced atomically. A kill anywhere leaves a
  curve that only names finished checkpoints; :meth:`resume` cuts the curve
  at the step training resumes from and :meth:`pending` says whether that
  step's validation is missing (killed before the curve was written).

  Args:
    folder: the model folder.
    rule: the plateau :class:`StopRule`.
    best: a :class:`~nlosjax.train.checkpoint.Checkpointer` for the best state (keep 1).
    validate: ``(model_config, params) -> validation PSNR`` (dB), or a dict of scores holding
      the rule's ``metric`` (:meth:`StopRule.score`).
    learning_rate: ``step -> learning rate`` of the run's schedule (recorded with each point).
    primary: whether this process writes the curve.
  """

  def __init__(self, folder, rule: StopRule, best, validate: Callable[[Any, Any], float],
               learning_rate: Callable[[int], float], *, primary: bool = True):
    self.path = pathlib.Path(folder) / CURVE_FILE
    self.rule = rule
    self.best = best
    self.validate = validate
    self.learning_rate = learning_rate
    self.primary = primary
    self.curve: list[dict] = []
    self._time_base = 0.0
    self._t0 = time.perf_counter()

  @property
  def scores(self) -> list[float]:
    """The deciding score of each point: ``score`` where the rule's metric is not the PSNR, else ``val_psnr``."""
    return [p.get("score", p["val_psnr"]) for p in self.curve]

  def resume(self, start: int) -> None:
    """Read the curve written before a kill, keeping the points up to step ``start``."""
    saved = read_curve(self.path.parent)
    if saved is not None and saved.get("rule") not in (None, self.rule.to_dict()):
      raise ValueError(f"{self.path} was written under another stopping rule:\n"
                       f"  file:     {saved.get('rule')}\n  this run: {self.rule.to_dict()}\n"
                       "use another --workdir or the matching train.stop")
    self.curve = [p for p in (saved or {}).get("curve", []) if p["step"] <= start]
    self._time_base = self.curve[-1]["time_s"] if self.curve else 0.0
    self._t0 = time.perf_counter()

  def pending(self, start: int) -> bool:
    """Whether step ``start`` is a validation step that the curve lacks (a kill between save and curve)."""
    return self.rule.validates_at(start) and not any(p["step"] == start for p in self.curve)

  def reason(self, steps_done: int) -> str | None:
    """:func:`stop_reason` of the curve so far."""
    return stop_reason(self.rule, self.scores, steps_done)

  @property
  def best_step(self) -> int | None:
    return self.curve[best_index(self.scores)]["step"] if self.curve else None

  def record(self, mcfg, state, step: int, to_host: Callable) -> float:
    """Validate ``state`` (at ``step``), save it as the best if it is, write the curve; returns the PSNR."""
    t0 = time.perf_counter()
    score, scores = self.rule.score(self.validate(mcfg, to_host(state.params)))
    val_s = time.perf_counter() - t0
    point = {"step": int(step), "val_psnr": scores.get("psnr", score)}
    if len(scores) > 1:
      point["val"] = scores
    if self.rule.metric != "psnr":
      point["score"] = score
    self.curve.append({**point, "time_s": round(self._time_base + time.perf_counter() - self._t0, 3),
                       "val_s": round(val_s, 3), "lr": float(self.learning_rate(step))})
    if self.best_step == step and step not in self.best.all_steps():
      self.best.save(state, step, force=True)
      self.best.wait()
    self.write()
    return score

  def summary(self, steps_done: int) -> dict:
    """The curve file's contents after ``steps_done`` steps."""
    best = best_index(self.scores) if self.curve else None
    out = {"rule": self.rule.to_dict(), "curve": self.curve,
           "best_step": None if best is None else self.curve[best]["step"],
           "best_val_psnr": None if best is None else self.curve[best]["val_psnr"],
           "steps_taken": int(steps_done), "stop_reason": self.reason(steps_done)}
    if self.rule.metric != "psnr":
      out["best_score"] = None if best is None else self.scores[best]
    return out

  def write(self, steps_done: int | None = None) -> None:
    if self.primary:
      steps = self.curve[-1]["step"] if steps_done is None and self.curve else (steps_done or 0)
      _write_json(self.path, self.summary(steps))

  def best_state(self, state):
    """The best state on validation, restored from ``best_checkpoint/`` (``state`` gives the structure)."""
    step = self.best_step
    if step is None:
      raise ValueError(f"{self.path.parent}: no validation was recorded, so there is no best state")
    if step not in self.best.all_steps():
      raise ValueError(f"{self.best.directory} lacks step {step}, the best on validation in "
                       f"{self.path} (kept: {self.best.all_steps()}); move the model folder away "
                       "to train it again")
    best, _ = self.best.restore(state, step)
    return best
