"""One command for an accelerator machine: correctness, scan kernels and paper scale on the device present.

    PYTHONPATH=. python -m benchmarks.device [--out DIR] [--budget-s 480] [--tiny]
    python -m benchmarks.device --collect DIR [--results benchmarks/results/device.md]
    python -m benchmarks.device --make-reference          # on CPU; rewrites benchmarks/device_reference/

Procedure on a GPU machine, which needs no network and no install step (JAX with CUDA, flax,
optax, orbax-checkpoint, h5py, chex, scipy and matplotlib; tqdm is optional; docs/gpu.md):

1. From the repository root, run

       PYTHONPATH=. python -m benchmarks.device --out DIR

   under a wall-clock limit below 10 minutes (e.g. ``timeout 560`` in front of it, for the
   default ``--budget-s 480``). It needs no install step
   and no network: only the tree, ``nlosjax/data/scans/`` (the shipped scan) and
   ``benchmarks/device_reference/reference.npz`` (the CPU values the checks compare with).
   The command manages the budget itself: each part gets a share of it (environment 3 %,
   correctness 20 %, scan kernels 22 %, paper scale 38 %, classic 17 %, unused time rolls
   over to the next part), skips a step or a part, with a note, whose conservative estimate
   exceeds the time left, and stops itself at ``--budget-s`` (``os._exit``) if a step overruns.
2. What comes back (``DIR``, 6 files): ``environment.json``, ``correctness.json``,
   ``scan_kernels.json``, ``paper_scale.json``, ``classic.json`` and ``device.log``. Each part's
   JSON is written when the part starts and rewritten after every row, so a run cut off still
   returns what it measured (``"status": "cut off"`` where the budget stopped it, ``"running"``
   where something outside killed it; ``"skipped"`` where it never had the time to start).
   The exit status is 1 when a correctness check failed or a part raised, else 0.
3. Back on any machine with the repository, ``python -m benchmarks.device --collect DIR`` (DIR: the folder that
   came back) writes ``benchmarks/results/device.md`` whole: the provenance lines recorded on the
   device (its device kind and date), the command, each part's table, and the goals
   shown as met / not met from the numbers; then ``python -m benchmarks.index``.

Parts, in this order (``benchmarks/device_parts.py``):

* **environment**: device kind and count, ``memory_stats()``, the driver (``nvidia-smi`` or
  ``/proc/driver/nvidia/version``, when present), jax / jaxlib / flax / optax versions, host CPU.
* **correctness**: every ``nlosjax.ssm`` scan method (causal and reverse, chunk 5) against a
  float64 NumPy loop of the recurrence and its adjoint (outputs, final state, seven gradients);
  each classic method on the shipped exit-sign scan against the CPU max-projection in
  ``benchmarks/device_reference/reference.npz`` (NCC); one train step of the cpu preset's Ours
  on a fixed batch and fixed synthetic parameters, loss and gradient global norm against the CPU
  values there (matmuls at float32 precision on the device). Limits: ``device_parts.SCAN_RTOL``,
  ``CLASSIC_NCC``, ``TRAIN_RTOL``.
* **scan kernels**: ``benchmarks.scan.bench_shape`` (imported) at its default shapes and at the
  paper model's temporal and spatial SSM shapes (training batch 4), every method forward and
  forward+backward, ratios to the exp floor of the same run, and what ``auto`` resolves to.
* **classic**: ms per frame of FBP, LCT, f-k, phasor and RSD at 128 x 128 x 512 against each
  method's FFT floor (``benchmarks.physics.fft_floor``), timed alternately.
* **paper scale** (last: the longest): the paper preset's Ours (``ModelConfig.paper()``, 128 x 128
  x 512): inference at batch 1 first, then the train step at the preset's batch (or the largest
  the plan fits) as two programs side by side (``device_parts.train_paths``): the **GPU path**
  (every ``nlosjax.platforms`` switch on its accelerator branch) first, then the **CPU-tuned
  path** (every switch on its CPU branch, forced with ``nlosjax.platforms.cpu_paths``) at the
  same batch where its estimate (``device_parts.cpu_tuned_estimate``: a second compile of the
  step and a step of unknown length) fits the time left, else skipped with a note. Each row:
  compile, one step for the device's ``peak_bytes_in_use`` (less what was held before the step
  besides its arguments; the second program's peak is hidden where the first's was higher)
  against the dry run's plan for this device (``nlosjax.plan``: ``compile_train_step`` and its
  ``memory_analysis()``), timed steps (the two programs alternated once both are compiled),
  seconds per step and the achieved FLOP/s (the program's FLOPs as the dry run counts them)
  against the device's float32 and TF32 peaks; one more step under ``jax.profiler``: each HLO
  op's device time and share by category (``benchmarks/op_profile.py``), the GPU path's always,
  the CPU-tuned path's where the time allows; then inference at batch 2, 4, ... until a
  failure, the budget or 1024.
* then a log note where a future mechanism study's rows would go (not implemented).

Goals, judged by ``--collect``: paper-scale inference >= 30 frames/s at batch 1 on one
H100; the paper train step at batch 4 <= 1 s on the GPU path; the dry run's planned peak
within +-20 % of the measured one (the GPU path's step); the best scan method's
forward+backward <= 6x the exp floor at every shape; the measured ``auto`` row within 10 % of the
best method, forward and forward+backward; every correctness check passes.

``--tiny`` runs the same functions on tiny shapes on CPU (``device_parts.TINY``: the cpu preset's
model cut down at 16 x 16 x 64, classic methods at 32 x 32 x 128, inference up to batch 2, both
train-step paths, the GPU path forced with ``nlosjax.platforms.accelerator_paths``) in
about 30-90 s on 2 cores; ``tests/test_device.py`` runs it and ``--collect`` on its folder.
The correctness reference holds both sizes; ``--make-reference`` rebuilds it on CPU.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import pathlib
import sys
import threading
import time
import traceback

from benchmarks import op_profile

HERE = pathlib.Path(__file__).resolve().parent
DEFAULT_RESULTS = HERE / "results" / "device.md"
REFERENCE = HERE / "device_reference" / "reference.npz"
LOG = "device.log"
#: (part, share of the budget, seconds needed to start it: full run, --tiny).
#: The classic part runs before the paper-scale one: a paper-scale train step leaves the
#: allocator's pool too full for the classic methods' operators.
PARTS = (("environment", 0.03, 5, 2), ("correctness", 0.20, 60, 10), ("scan_kernels", 0.22, 30, 5),
         ("classic", 0.17, 30, 5), ("paper_scale", 0.38, 120, 15))
MARGIN_S = 5.0
GOAL_FPS, GOAL_MEMORY = 30.0, 0.20
#: The paper train step's goal, judged on the GPU path: seconds per step at this batch.
GOAL_STEP_S, GOAL_STEP_BATCH = 1.0, 4


def _jsonable(v):
  if isinstance(v, dict):
    return {str(k): _jsonable(x) for k, x in v.items()}
  if isinstance(v, (list, tuple)):
    return [_jsonable(x) for x in v]
  if hasattr(v, "item") and getattr(v, "ndim", 1) == 0:
    return v.item()
  return v


def _write_json(path: pathlib.Path, data: dict) -> None:
  tmp = path.with_name(path.name + ".tmp")
  tmp.write_text(json.dumps(_jsonable(data), indent=1, default=str))
  os.replace(tmp, path)


class Run:
  """The run's clock, log and output folder."""

  def __init__(self, out: pathlib.Path, budget_s: float, tiny: bool, command: str, reference: pathlib.Path):
    self.out, self.budget_s, self.tiny, self.command = out, float(budget_s), tiny, command
    self.reference_path = reference
    self.t0 = time.perf_counter()
    self.current = None
    out.mkdir(parents=True, exist_ok=True)
    for name in [f"{part}.json" for part, *_ in PARTS] + [LOG]:   # an earlier run's files: not this run's
      (out / name).unlink(missing_ok=True)
    self._log = open(out / LOG, "a")

  def elapsed(self) -> float:
    return time.perf_counter() - self.t0

  def log(self, msg: str, flush: bool = True) -> None:
    line = f"[{self.elapsed():7.1f} s] {msg}"
    print(line, flush=True)
    self._log.write(line + "\n")
    self._log.flush()

  def close(self) -> None:
    self._log.close()


class Part:
  """What a part function sees (``benchmarks/device_parts.py``): its data, the clock, the log."""

  def __init__(self, run: Run, name: str, deadline: float):
    self.run, self.name, self.deadline = run, name, deadline
    self.tiny, self.command, self.log = run.tiny, run.command, run.log
    self.data = {"part": name, "status": "running", "tiny": run.tiny, "notes": [],
                 "started_s": round(run.elapsed(), 2)}
    self._reference = None

  @property
  def path(self) -> pathlib.Path:
    return self.run.out / f"{self.name}.json"

  def save(self) -> None:
    _write_json(self.path, self.data)

  def left(self) -> float:
    return self.deadline - self.run.elapsed()

  def total_left(self) -> float:
    return self.run.budget_s - MARGIN_S - self.run.elapsed()

  def fits(self, estimate_s: float, what: str) -> bool:
    """Whether ``what`` (estimated ``estimate_s``) fits the time left to this part; a note where not."""
    left = self.left()
    if estimate_s <= left:
      return True
    note = f"skipped {what}: estimated {estimate_s:.0f} s, {max(left, 0):.0f} s left to this part"
    self.data["notes"].append(note)
    self.data.setdefault("skipped", []).append(what)
    self.save()
    self.log(note)
    return False

  def reference(self) -> dict:
    """This size's CPU values from the reference file (``--make-reference``)."""
    if self._reference is None:
      import numpy as np
      prefix = "tiny_" if self.tiny else "full_"
      with np.load(self.run.reference_path) as z:
        self._reference = {k[len(prefix):]: z[k] for k in z.files if k.startswith(prefix)}
    return self._reference


def _watchdog(run: Run) -> threading.Timer:
  def stop():
    part = run.current
    if part is not None:
      part.data["status"] = "cut off"
      part.data["notes"].append(f"cut off: the budget of {run.budget_s:.0f} s ran out in this part")
      try:
        part.save()
      except OSError:
        pass
    run.log(f"budget of {run.budget_s:.0f} s spent during {part.name if part else 'no part'}: stopping; "
            "finished rows are written")
    os._exit(3)
  timer = threading.Timer(run.budget_s, stop)
  timer.daemon = True
  timer.start()
  return timer


def run_parts(run: Run) -> int:
  """Every part in order, each within its share of the budget; 1 if a check failed or a part raised."""
  from benchmarks import device_parts as parts
  usable = run.budget_s - MARGIN_S
  ends, total = [], 0.0
  for _, share, _, _ in PARTS:
    total += share
    ends.append(min(total, 1.0) * usable)
  failed = False
  run.log(f"{'tiny rehearsal' if run.tiny else 'device run'}: budget {run.budget_s:.0f} s, out {run.out}")
  for (name, _, need_full, need_tiny), end in zip(PARTS, ends):
    part = Part(run, name, end)
    run.current = part
    need = need_tiny if run.tiny else need_full
    if part.left() < need:
      part.data["status"] = "skipped"
      part.fits(need, f"the {name} part")
      continue
    run.log(f"--- {name} (until {end:.0f} s)")
    part.save()
    try:
      getattr(parts, name)(part)
      part.data["status"] = "done"
    except Exception as e:                         # noqa: BLE001 - the next part still runs
      failed = True
      part.data.update(status="failed", error=f"{type(e).__name__}: {e}", traceback=traceback.format_exc())
      run.log(f"{name} failed: {type(e).__name__}: {e}")
    part.data["seconds"] = round(run.elapsed() - part.data["started_s"], 2)
    part.save()
    failed |= any(not c["ok"] for c in part.data.get("checks", ()))
  run.current = None
  parts.future_mechanism_study(Part(run, "future_mechanism_study", run.budget_s))
  run.log(f"done in {run.elapsed():.0f} s")
  return int(failed)


def make_reference(path: pathlib.Path) -> int:
  import jax
  import numpy as np

  from benchmarks import device_parts as parts
  from experiments import provenance
  if jax.default_backend() != "cpu":
    print("--make-reference runs on CPU (JAX_PLATFORMS=cpu): the reference is the CPU's answer", file=sys.stderr)
    return 2
  out = {}
  for tiny in (False, True):
    t = time.perf_counter()
    for k, v in parts.make_reference(tiny).items():
      out[("tiny_" if tiny else "full_") + k] = v
    print(f"{'tiny' if tiny else 'full'} reference in {time.perf_counter() - t:.0f} s")
  meta = {"command": "python -m benchmarks.device --make-reference", "commit": provenance.git_commit(),
          "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
          "machine": provenance.cpu_model(), "jax": jax.__version__,
          "train": {"full": parts.FULL["train"][:3], "tiny": parts.TINY["train"][:3]},
          "classic_options": parts.CLASSIC_OPTIONS, "depth_range": parts.DEPTH_RANGE}
  out["meta"] = np.array(json.dumps(_jsonable(meta), default=str))
  path.parent.mkdir(parents=True, exist_ok=True)
  np.savez_compressed(path, **out)
  print(f"wrote {path} ({path.stat().st_size} bytes): loss {out['full_loss']:.6g}, grad norm "
        f"{out['full_grad_norm']:.6g} (tiny {out['tiny_loss']:.6g}, {out['tiny_grad_norm']:.6g})")
  return 0


# ------------------------------------------------------------------------ collect
def _load(folder: pathlib.Path, name: str) -> dict | None:
  path = folder / f"{name}.json"
  try:
    return json.loads(path.read_text())
  except (OSError, ValueError):
    return None


def _f(v, spec=".2f", none="-") -> str:
  return none if v is None else format(v, spec)


def _gib(b) -> str:
  return "-" if b is None else f"{b / 2 ** 30:.2f}"


def _verdict(ok) -> str:
  return "not measured" if ok is None else ("met" if ok else "**not met**")


def goals(data: dict) -> list[tuple[str, bool | None, str]]:
  """``(goal, met or None where not measured, the numbers)`` for each goal (module docstring)."""
  from benchmarks import scan as scan_bench
  env, corr, scan, paper = (data.get(k) or {} for k in ("environment", "correctness", "scan_kernels",
                                                       "paper_scale"))
  out = []
  inf = [r for r in paper.get("inference", []) if "fps" in r]
  one = next((r for r in inf if r["batch"] == 1), None)
  kind = env.get("device_kind", "?")
  if one:
    best = max(inf, key=lambda r: r["fps"])
    out.append((f"paper-scale inference >= {GOAL_FPS:g} frames/s on one H100 (batch 1)", one["fps"] >= GOAL_FPS,
                f"{one['fps']:.1f} frames/s at batch 1 on {kind}; {best['fps']:.1f} at batch {best['batch']}"))
  else:
    out.append((f"paper-scale inference >= {GOAL_FPS:g} frames/s on one H100 (batch 1)", None, "no batch-1 row"))
  tr = paper.get("train") or {}
  out.append(_step_goal(tr, paper.get("train_cpu_tuned") or {}, paper.get("train_paths") or {}, kind))
  meas, planned = tr.get("measured_peak_bytes"), tr.get("planned_peak_bytes")
  name = f"dry-run memory within +-{GOAL_MEMORY:.0%} of the measured peak (train step)"
  if meas and planned and tr.get("attributable", True):
    err = planned / meas - 1
    out.append((name, abs(err) <= GOAL_MEMORY, f"planned {_gib(planned)} GiB, measured {_gib(meas)} GiB ({err:+.1%})"))
  else:
    out.append((name, None, tr.get("memory_note") or ("an earlier part's peak was higher: the step's is not "
                                                      "visible" if meas else "no measurement")))
  fb, au = [], []
  failed = [f"{s['shape']}: failed ({s['error']})" for s in scan.get("shapes", []) if "error" in s]
  for s in scan.get("shapes", []):
    rows = {(r["method"], r["pass"]): r for r in s.get("rows", [])}
    concrete = [m for m in scan_bench.METHODS if m != "auto" and (m, "fwd+bwd") in rows]
    if not concrete:
      continue
    best = {p: min(concrete, key=lambda m: rows[(m, p)]["ms"]) for p in ("fwd", "fwd+bwd")}
    fb.append((s["shape"], best["fwd+bwd"], rows[(best["fwd+bwd"], "fwd+bwd")]["x_floor"]))
    if ("auto", "fwd") in rows:
      au.append((s["shape"], s["auto"], *(rows[("auto", p)]["ms"] / rows[(best[p], p)]["ms"] for p in best)))
  # A shape that failed (e.g. out of memory) counts as not met: the goal is for every shape.
  out.append((f"scan fwd+bwd <= {scan_bench.GOAL_FWDBWD:g}x the exp floor (best method, every shape)",
              (not failed and all(r <= scan_bench.GOAL_FWDBWD for *_, r in fb)) if fb or failed else None,
              "; ".join([f"{s}: {m} {r:.2f}x" for s, m, r in fb] + failed) or "no shape measured"))
  out.append((f"`auto` within {scan_bench.GOAL_AUTO - 1:.0%} of the best (fwd and fwd+bwd, every shape)",
              (not failed and all(f <= scan_bench.GOAL_AUTO and b <= scan_bench.GOAL_AUTO for *_, f, b in au))
              if au or failed else None,
              "; ".join([f"{s}: auto -> {a}, {f:.2f}x / {b:.2f}x the best" for s, a, f, b in au] + failed)
              or "no shape measured"))
  checks = corr.get("checks", [])
  done = corr.get("status") == "done"
  out.append(("every correctness check passes", (all(c["ok"] for c in checks) and done) if checks else None,
              f"{sum(c['ok'] for c in checks)} of {len(checks)} passed" + ("" if done else
                                                                            f"; part {corr.get('status', 'absent')}")))
  return out


def _step_goal(gpu: dict, cpu: dict, paths: dict, kind: str) -> tuple[str, bool | None, str]:
  """The paper train step's goal on the GPU path's row; the CPU-tuned path's time beside it."""
  name = f"paper train step at batch {GOAL_STEP_BATCH} <= {GOAL_STEP_S:g} s (GPU path)"
  if "step_s" not in gpu:
    return name, None, gpu.get("error") or "no GPU-path step"
  beside = ""
  if "step_s" in cpu:
    ratio = paths.get("ratio", cpu["step_s"] / gpu["step_s"])
    beside = f"; CPU-tuned path {cpu['step_s']:.3f} s ({ratio:.2f}x)"
  took = f"{gpu['step_s']:.3f} s at batch {gpu['batch']} on {kind}{beside}"
  if gpu["batch"] == GOAL_STEP_BATCH:
    return name, gpu["step_s"] <= GOAL_STEP_S, took
  if gpu.get("batch_reduced_from") == GOAL_STEP_BATCH:
    return name, False, f"batch {GOAL_STEP_BATCH} does not fit the plan; {took}"
  return name, None, f"not run at batch {GOAL_STEP_BATCH}: {took}"


def render(folder: pathlib.Path, collect_command: str) -> str:
  from experiments import provenance
  data = {name: _load(folder, name) for name, *_ in PARTS}
  env = data["environment"] or {}
  tiny = any((d or {}).get("tiny") for d in data.values())
  kind = env.get("device_kind", "unknown device")
  lines = [f"# Device run{' (tiny CPU rehearsal)' if tiny else ''}: correctness, scan kernels and paper scale"
           f" on {kind}", ""]
  head = list(env.get("provenance") or ["Produced by `python -m benchmarks.device` (no environment part).",
                                        "", "- Machine: unknown", "- Commit: unknown"])
  for i, line in enumerate(head):
    if line.startswith("Produced by"):
      head[i] = line.rstrip(".") + f" on the device; collected by `{collect_command}`."
    elif line.startswith("- Machine: "):
      mem = (env.get("memory_stats") or {}).get("bytes_limit")
      head[i] = (f"- Machine: {kind} ({env.get('device_count', '?')} x {env.get('platform', '?')}"
                 + (f", allocator limit {mem / 2 ** 30:.1f} GiB" if mem else "")
                 + "); host " + line[len("- Machine: "):])
    elif line.startswith("- Commit: ") and line.split()[2] == "unknown":
      head[i] = (f"- Commit: unknown on the device (its copy had no git); collected at "
                 f"{provenance.git_commit()}")
  lines += head + [""]
  drv = env.get("driver") or {}
  v = env.get("versions") or {}
  lines += [f"- Device: {kind}; driver {'; '.join(drv.get('nvidia_smi', [])) or drv.get('proc_driver') or 'n/a'}; "
            f"jax {v.get('jax')}, jaxlib {v.get('jaxlib')}, flax {v.get('flax')}, optax {v.get('optax')}, "
            f"CUDA plugin {v.get('jax-cuda12-plugin') or v.get('jax-cuda13-plugin') or 'none'}; "
            f"plan memory {_gib((env.get('plan_memory') or {}).get('bytes'))} GiB "
            f"({(env.get('plan_memory') or {}).get('source', '?')})",
            "- Parts: " + ", ".join(f"{n} {(data[n] or {}).get('status', 'absent (no file)')}"
                                     + (f" ({data[n]['seconds']:.0f} s)" if (data[n] or {}).get("seconds") else "")
                                     for n, *_ in PARTS), ""]
  if tiny:
    lines += ["This is the `--tiny` rehearsal: tiny shapes on CPU, the same code paths; its numbers say nothing"
              " about the paper scale.", ""]
  lines += ["## Goals", ""] + [f"- {g}: {_verdict(ok)} ({why})" for g, ok, why in goals(data)] + [""]
  lines += _correctness_md(data["correctness"]) + _scan_md(data["scan_kernels"]) + _paper_md(data["paper_scale"])
  lines += _classic_md(data["classic"])
  notes = [f"- {n}: {note}" for n, *_ in PARTS for note in (data[n] or {}).get("notes", [])]
  errors = [f"- {n}: {(data[n] or {})['error']}" for n, *_ in PARTS if (data[n] or {}).get("error")]
  if notes or errors:
    lines += ["## Notes", ""] + errors + notes + [""]
  return "\n".join(lines)


def _correctness_md(d) -> list[str]:
  if not d:
    return ["## Correctness", "", "Not run.", ""]
  lim = d.get("limits", {})
  out = ["## Correctness", "",
         f"Scans (float32) against a float64 NumPy loop: worst relative error of y, the final state and the seven "
         f"gradients, limit {lim.get('scan_rel')}; `auto` resolves to {d.get('auto')} at that shape. Classic methods:"
         f" max-projection NCC with the CPU reference, limit {lim.get('classic_ncc')}. Train step: relative"
         f" difference from the CPU values, limit {lim.get('train_rel')} (matmul precision "
         f"{(d.get('train') or {}).get('precision', '?')}).", "",
         "| check | value | limit | passed |", "|---|---|---|---|"]
  out += [f"| {c['name']} | {_f(c['value'], '.3g', c.get('error', '-'))} | {c['limit']:g} | "
          f"{'yes' if c['ok'] else '**no**'} |" for c in d.get("checks", [])]
  return out + [""]


def _scan_md(d) -> list[str]:
  if not d:
    return ["## Scan kernels", "", "Not run.", ""]
  out = ["## Scan kernels", "", f"`benchmarks.scan.bench_shape`, median of {d.get('repeats')} interleaved calls;"
         " `x floor` = time / exp-floor time of the same shape; peak from `memory_analysis()`.", "",
         "| shape | origin | method | fwd ms | x floor | fwd+bwd ms | x floor | fwd+bwd peak MB |",
         "|---|---|---|---|---|---|---|---|"]
  for s in d.get("shapes", []):
    if "error" in s:
      out.append(f"| {s['shape']} | {s['origin']} | failed: {s['error']} | | | | | |")
      continue
    rows = {(r["method"], r["pass"]): r for r in s["rows"]}
    for m in dict.fromkeys(r["method"] for r in s["rows"]):
      f, b = rows.get((m, "fwd"), {}), rows.get((m, "fwd+bwd"), {})
      label = f"auto [{s['auto']}]" if m == "auto" else m
      out.append(f"| {s['shape']} | {s['origin']} | {label} | {_f(f.get('ms'))} | {_f(f.get('x_floor'))} | "
                 f"{_f(b.get('ms'))} | {_f(b.get('x_floor'))} | {_f(b.get('peak_mb'), '.1f')} |")
  return out + [""]


def _paper_md(d) -> list[str]:
  if not d:
    return ["## Paper scale", "", "Not run.", ""]
  out = ["## Paper scale", "", f"The `{d.get('preset')}` preset's `{d.get('variant')}`, Setup {d.get('setup')}"
         f" (grid and bins), input {d.get('input')} per sample; synthetic fixed parameters.", ""]
  out += _train_md(d)
  out += ["### Inference", "", "| batch | ms per step | ms per frame | frames/s | compile s | planned peak GiB |",
          "|---|---|---|---|---|---|"]
  for r in d.get("inference", []):
    if "error" in r:
      out.append(f"| {r['batch']} | failed: {r['error']} | | | | |")
    else:
      out.append(f"| {r['batch']} | {r['step_s'] * 1e3:.2f} | {r['ms_per_frame']:.2f} | {r['fps']:.1f} | "
                 f"{r['compile_s']:.1f} | {_gib(r['planned_peak_bytes'])} |")
  return out + ["", f"Largest batch that ran: {d.get('largest_batch')}.", ""]


#: The train step's rows in ``paper_scale.json``: (key, label where the row has none).
TRAIN_ROWS = (("train", "GPU path"), ("train_cpu_tuned", "CPU-tuned path"))


def _fraction(achieved, peak) -> str:
  return "-" if not achieved or not peak else f"{achieved / peak:.1%}"


def _train_md(d: dict) -> list[str]:
  """The train step's two programs side by side, then each one's per-op profile."""
  rows = [(d.get(key) or {}, label) for key, label in TRAIN_ROWS]
  if not any(r for r, _ in rows):
    return []
  out = ["### The train step: GPU path and CPU-tuned path", "",
         "The same step compiled twice on this device: every `nlosjax.platforms` switch on its accelerator branch"
         " (GPU path, what the library runs on a GPU) or on its CPU branch (CPU-tuned path, what it runs on a"
         " CPU); a path that is not the device's own is forced (`nlosjax.platforms.cpu_paths()` or"
         " `accelerator_paths()`) and marked so. The same batch, synthetic state and data. Seconds per step: median of"
         " the timed steps (the two programs alternated once both were compiled); FLOP/s: the program's FLOPs as"
         " the dry run counts them (XLA's count plus FFT and scan estimates) over that time. Planned peak: the dry"
         " run's `memory_analysis()` on this device; measured: `peak_bytes_in_use` less memory held before the"
         " step by anything but its arguments (hidden, `-`, where an earlier peak was higher).", "",
         "| path | batch | s per step | steps timed | first step s | compile s | GFLOP a step | TFLOP/s |"
         " of float32 peak | of TF32 peak | planned peak GiB | measured peak GiB |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|"]
  for r, label in rows:
    name = r.get("label", label) + (" (forced)" if r.get("forced") else "")
    if "step_s" not in r:
      why = f"failed: {r['error']}" if r.get("error") else "not run (see the notes)"
      out.append(f"| {name} | {r.get('batch', '-')} | {why} | | | | | | | | {_gib(r.get('planned_peak_bytes'))} | |")
      continue
    f32, tf32 = r.get("peak_flops") or (None, None)
    meas = r.get("measured_peak_bytes") if r.get("attributable", True) else None
    batch = f"{r['batch']}" + (f" (of {r['batch_reduced_from']})" if r.get("batch_reduced_from") else "")
    out.append(f"| {name} | {batch} | {r['step_s']:.3f} | {r.get('steps_timed', 0)} | {_f(r.get('first_step_s'))} | "
               f"{_f(r.get('compile_s'), '.0f')}{' (reused)' if r.get('compile_reused') else ''} | "
               f"{_f(r.get('flops') and r['flops'] / 1e9, '.4g')} | "
               f"{_f(r.get('flop_per_s') and r['flop_per_s'] / 1e12, '.3g')} | {_fraction(r.get('flop_per_s'), f32)} | "
               f"{_fraction(r.get('flop_per_s'), tf32)} | {_gib(r.get('planned_peak_bytes'))} | {_gib(meas)} |")
  gpu, cpu = rows[0][0], rows[1][0]
  paths = d.get("train_paths") or {}
  if paths.get("ratio"):
    out += ["", f"CPU-tuned path / GPU path: {paths['ratio']:.2f}x the time a step (medians of {paths['pairs']} "
            f"pair(s) timed alternately: {paths['cpu_tuned_s']:.3f} s and {paths['gpu_s']:.3f} s)."]
  elif "step_s" in gpu and "step_s" in cpu:
    out += ["", f"CPU-tuned path / GPU path: {cpu['step_s'] / gpu['step_s']:.2f}x the time a step (not alternated)."]
  else:
    out += ["", "CPU-tuned path / GPU path: not measured (one of the rows did not run)."]
  notes = [f"{r.get('label', label)}: the preset's batch {r['batch_reduced_from']} does not fit the plan"
           for r, label in rows if r.get("batch_reduced_from")]
  memory_notes = {}                                  # note -> the rows that carry it
  for r, label in rows:
    if r.get("memory_note"):
      memory_notes.setdefault(r["memory_note"], []).append(r.get("label", label))
  notes += [f"{' and '.join(labels)}: {note}" for note, labels in memory_notes.items()]
  if gpu.get("device_memory"):
    notes.append(f"plan's device memory {_gib(gpu['device_memory'])} GiB ({gpu.get('device_memory_source')})")
  out += ["", "; ".join(notes) + "." if notes else "", ""]
  for r, label in rows:
    prof = r.get("profile")
    name = r.get("label", label)
    if prof and "error" in prof:
      out += [f"Per-op profile of the train step, {name}: failed ({prof['error']}).", ""]
    elif prof:
      out += [f"### Where the train step's time goes: {name}", "",
              "One step under `jax.profiler` (`benchmarks/op_profile.py`): each HLO op's device time, "
              "its category from the compiled HLO (a fusion by its heaviest op, a custom call by its target).",
              ""] + op_profile.format_profile(prof, r.get("flops"), r.get("peak_flops"))
  return out


def _classic_md(d) -> list[str]:
  if not d:
    return ["## Classic methods", "", "Not run.", ""]
  out = ["## Classic methods", "", f"{d.get('grid')} x {d.get('grid')} scan points, {d.get('bins')} bins"
         " (`benchmarks.physics.synthetic_transient`), default options; FFT floor = `benchmarks.physics.fft_floor`,"
         " timed alternately with the method.", "",
         "| method | ms per frame | FFT floor ms | x floor | compile s |", "|---|---|---|---|---|"]
  for r in d.get("rows", []):
    out.append(f"| {r['method']} | failed: {r['error']} | | | |" if "error" in r else
               f"| {r['method']} | {r['ms']:.2f} | {r['floor_ms']:.2f} | {r['x_floor']:.2f} | {r['compile_s']:.1f} |")
  return out + [""]


def collect(folder: pathlib.Path, results: pathlib.Path, command: str) -> int:
  text = render(folder, command)
  results.parent.mkdir(parents=True, exist_ok=True)
  results.write_text(text)
  print(text)
  print(f"wrote {results}")
  return 0


# --------------------------------------------------------------------------- main
def main(argv=None, *, hard_stop: bool = False) -> int:
  p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--out", type=pathlib.Path, default=pathlib.Path("runs/device"), help="output folder")
  p.add_argument("--budget-s", type=float, default=480.0, help="wall-clock budget, seconds (default 480)")
  p.add_argument("--tiny", action="store_true", help="the same code paths on tiny shapes (CPU, ~30-60 s)")
  p.add_argument("--collect", type=pathlib.Path, metavar="DIR", help="write the results file from a run's folder")
  p.add_argument("--results", type=pathlib.Path, default=DEFAULT_RESULTS, help="where --collect writes")
  p.add_argument("--make-reference", action="store_true", help="rebuild the CPU reference file (on CPU)")
  p.add_argument("--reference", type=pathlib.Path, default=REFERENCE, help=argparse.SUPPRESS)
  args = p.parse_args(argv)
  words = sys.argv[1:] if argv is None else list(argv)
  command = " ".join(["python -m benchmarks.device", *words])
  if args.collect is not None:
    return collect(args.collect, args.results, command)
  if args.make_reference:
    return make_reference(args.reference)
  if args.budget_s <= MARGIN_S:
    p.error(f"--budget-s must exceed {MARGIN_S:g}")
  run = Run(args.out, args.budget_s, args.tiny, command, args.reference)
  timer = _watchdog(run) if hard_stop else None
  try:
    return run_parts(run)
  finally:
    if timer is not None:
      timer.cancel()
    run.close()


if __name__ == "__main__":
  sys.exit(main(hard_stop=True))
