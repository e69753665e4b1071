"""``python -m benchmarks.device``: the tiny rehearsal runs every part, passes every check, and collects."""

import json

import jax
import pytest

from benchmarks import device
from nlosjax import plan

PART_NAMES = [name for name, *_ in device.PARTS]


@pytest.mark.full
def test_tiny_run_writes_every_part_passes_every_check_and_collects(tmp_path):
  out = tmp_path / "device"
  assert device.main(["--tiny", "--out", str(out)]) == 0
  files = sorted(p.name for p in out.iterdir())
  assert files == sorted([f"{n}.json" for n in PART_NAMES] + [device.LOG]) and len(files) <= 8
  parts = {n: json.loads((out / f"{n}.json").read_text()) for n in PART_NAMES}
  for name, d in parts.items():
    assert d["status"] == "done" and d["tiny"], (name, d.get("error"), d["notes"])
    assert not d["notes"] and "skipped" not in d, (name, d["notes"])
  checks = parts["correctness"]["checks"]
  assert len(checks) == 4 * 2 + 5 + 2 and all(c["ok"] for c in checks), [c for c in checks if not c["ok"]]
  assert {r["method"] for r in parts["classic"]["rows"]} == {"fbp", "lct", "fk", "phasor", "rsd"}
  assert all("x_floor" in r for r in parts["classic"]["rows"])
  assert [r["batch"] for r in parts["paper_scale"]["inference"]] == [1, 2]
  paper = parts["paper_scale"]
  gpu, cpu = paper["train"], paper["train_cpu_tuned"]              # the train step's two programs
  assert (gpu["path"], gpu["forced"]) == ("accelerator", True) and (cpu["path"], cpu["forced"]) == ("cpu", False)
  assert cpu["compile_reused"]                                     # on a CPU: the correctness part's program
  for row in (gpu, cpu):
    assert row["planned_peak_bytes"] > 0 and row["batch"] == 2 and row["step_s"] > 0 and row["flop_per_s"] > 0
    prof = row["profile"]                                          # the step's per-op profile
    assert "error" not in prof and prof["ops"] and prof["busy_ms"] <= prof["wall_ms"] * prof["lanes"]
    assert sum(c["share"] for c in prof["categories"].values()) == pytest.approx(1.0)
    assert "convolution" in prof["categories"]                     # the network's convolutions are there
  assert gpu["loss"] == pytest.approx(cpu["loss"], rel=1e-5)        # the same sums, two programs
  assert paper["train_paths"]["pairs"] == 2 and len(cpu["times_s"]) == 2 and len(gpu["times_s"]) == 4
  assert parts["scan_kernels"]["shapes"] and all("rows" in s for s in parts["scan_kernels"]["shapes"])
  assert "future mechanism study" in (out / device.LOG).read_text()

  results = tmp_path / "results" / "device.md"
  assert device.main(["--collect", str(out), "--results", str(results)]) == 0
  text = results.read_text()
  assert "Produced by `python -m benchmarks.device --tiny --out" in text and "- Machine: cpu" in text
  assert "- Commit: " in text and "(tiny CPU rehearsal)" in text
  assert "every correctness check passes: met (15 of 15 passed)" in text
  assert "| category | ms a step | share of busy |" in text
  for name in ("GPU path", "CPU-tuned path"):
    assert f"### Where the train step's time goes: {name}" in text
  assert "| GPU path (forced) | 2 | " in text and "| CPU-tuned path | 2 | " in text
  assert "CPU-tuned path / GPU path: " in text and "pair(s) timed alternately" in text
  for goal in ("- paper-scale inference >= 30 frames/s on one H100 (batch 1): ",
               "- paper train step at batch 4 <= 1 s (GPU path): not measured (not run at batch 4: ",
               "- dry-run memory within +-20% of the measured peak (train step): not measured (cpu: ",
               "- scan fwd+bwd <= 6x the exp floor (best method, every shape): ",
               "- `auto` within 10% of the best (fwd and fwd+bwd, every shape): "):
    assert goal in text, goal


@pytest.mark.full
def test_a_budget_too_small_skips_parts_with_a_note_and_still_collects(tmp_path):
  out = tmp_path / "device"
  assert device.main(["--tiny", "--out", str(out), "--budget-s", "6"]) == 0
  for name in PART_NAMES:
    d = json.loads((out / f"{name}.json").read_text())
    assert d["status"] == "skipped" and d["notes"][0].startswith(f"skipped the {name} part"), d
  results = tmp_path / "device.md"
  device.main(["--collect", str(out), "--results", str(results)])
  assert "every correctness check passes: not measured" in results.read_text()


class _Accelerator:
  """A device as JAX describes a GPU: its allocator's limit in ``memory_stats()``."""

  platform = "gpu"

  def __init__(self, stats):
    self.stats = stats

  def memory_stats(self):
    if isinstance(self.stats, Exception):
      raise self.stats
    return self.stats


def test_the_dry_run_plans_for_the_accelerators_memory_and_keeps_the_cpus():
  limit = 60 * 2 ** 30
  assert plan.device_memory(_Accelerator({"bytes_limit": limit, "bytes_in_use": 1})) == (
      limit, "gpu memory_stats()['bytes_limit']")
  assert plan.device_memory(_Accelerator({}))[0] is None
  assert plan.device_memory(_Accelerator(NotImplementedError()))[0] is None
  cpu_bytes, source = plan.device_memory(jax.devices("cpu")[0])
  assert cpu_bytes > 0 and source.startswith("host")


def test_the_train_steps_peak_and_the_batch_that_fits_as_on_an_accelerator():
  from benchmarks import device_parts as parts
  gib = 2 ** 30
  p = plan.StepPlan("train", batch=4, devices=1, argument_bytes=gib, output_bytes=gib, temp_bytes=40 * gib,
                    alias_bytes=gib, flops=1.0, compile_s=1.0)        # 41 GiB: 1 fixed + 10 per sample
  assert parts.fitting_batch(p, 60 * gib) is None                     # batch 4 fits 0.9 x 60 GiB
  assert parts.fitting_batch(p, 40 * gib) == 3 and parts.fitting_batch(p, 13 * gib) == 1
  assert parts.fitting_batch(p, 10 * gib) is None and parts.fitting_batch(p, None) is None
  before = {"bytes_in_use": 3 * gib, "peak_bytes_in_use": 5 * gib}   # 1 GiB arguments + 2 GiB of others
  got = parts.step_peak(before, {"bytes_in_use": 3 * gib, "peak_bytes_in_use": 42 * gib}, gib)
  assert got["measured_peak_bytes"] == 40 * gib and got["attributable"]
  assert not parts.step_peak(before, {"peak_bytes_in_use": 5 * gib}, gib)["attributable"]
  assert parts.step_peak({}, {}, gib)["measured_peak_bytes"] is None


# ------------------------------------------------- the train step's two paths, scheduled
def _fake_paths(monkeypatch, tmp_path, left_s: float, gpu_s: float = 0.8, cpu_s: float = 14.0):
  """``device_parts.train_paths`` at full size with its compiles and steps faked: (part, calls made).

  The GPU path compiles in 130 s and runs ``gpu_s`` a step, the CPU-tuned path ``cpu_s``; the
  part has ``left_s`` seconds left.
  """
  from benchmarks import device_parts as parts
  calls = []

  def step_row(ctx, key, cfg, variant, path, reduce):
    calls.append(("compile", key))
    row = {"path": path, "label": dict((k, lab) for k, _, lab in parts.TRAIN_PATHS)[key], "batch": 4,
           "compile_s": 130.0, "flops": 2e12, "times_s": [], "first_step_s": 2 * (gpu_s if key == "train" else cpu_s)}
    parts._step_time(row)
    ctx.data[key] = row
    return row, {"cfg": cfg, "t": gpu_s if key == "train" else cpu_s, "key": key}

  def run_step(run):
    calls.append(("step", run["key"]))
    return run["t"]
  monkeypatch.setattr(parts, "_step_row", step_row)
  monkeypatch.setattr(parts, "_run_step", run_step)
  monkeypatch.setattr(parts, "_step_profile", lambda ctx, row, run: calls.append(("profile", run["key"])))
  monkeypatch.setattr(parts, "is_compiled", lambda *a, **k: False)
  run = device.Run(tmp_path / "out", 1e4, False, "test", device.REFERENCE)
  part = device.Part(run, "paper_scale", run.elapsed() + left_s)
  parts.train_paths(part, {"train": {"batch_size": 4}}, "ours")
  run.close()
  return part, calls


def test_the_gpu_path_runs_first_and_the_cpu_tuned_path_is_skipped_where_it_would_not_fit(monkeypatch, tmp_path):
  from benchmarks import device_parts as parts
  part, calls = _fake_paths(monkeypatch, tmp_path, left_s=150.0)
  # A second compile (at least 1.2 x the GPU path's) and a step of unknown length: over 150 s.
  assert parts.cpu_tuned_estimate(part, part.data["train"], {}, "ours") == pytest.approx(1.2 * 130 + 20 + 10)
  assert calls == [("compile", "train")] + [("step", "train")] * 3 + [("profile", "train")]
  assert "train_cpu_tuned" not in part.data and "train_paths" not in part.data
  assert part.data["notes"] == ["skipped the CPU-tuned path's train step: estimated 186 s, 150 s left to this part"]
  assert part.data["train"]["step_s"] == 0.8 and part.data["train"]["flop_per_s"] == pytest.approx(2e12 / 0.8)
  text = "\n".join(device._paper_md({**part.data, "inference": []}))
  assert "| CPU-tuned path | - | not run (see the notes) |" in text and "not measured (one of the rows" in text
  data = {"environment": {"device_kind": "NVIDIA H100"}, "paper_scale": part.data}
  (goal,) = [g for g in device.goals(data) if g[0].startswith("paper train step")]
  assert goal == ("paper train step at batch 4 <= 1 s (GPU path)", True, "0.800 s at batch 4 on NVIDIA H100")


def test_with_the_time_both_paths_run_alternated_and_the_ratio_is_theirs(monkeypatch, tmp_path):
  part, calls = _fake_paths(monkeypatch, tmp_path, left_s=1e3, gpu_s=1.5)
  pairs = [("step", "train"), ("step", "train_cpu_tuned")] * 3
  assert calls == ([("compile", "train")] + [("step", "train")] * 3 + [("profile", "train"),
                   ("compile", "train_cpu_tuned")] + pairs + [("profile", "train_cpu_tuned")])
  assert part.data["train_paths"] == {"pairs": 3, "gpu_s": 1.5, "cpu_tuned_s": 14.0, "ratio": 14.0 / 1.5}
  assert not part.data["notes"]
  text = "\n".join(device._paper_md({**part.data, "inference": []}))
  assert "CPU-tuned path / GPU path: 9.33x the time a step (medians of 3 pair(s) timed alternately" in text
  data = {"environment": {"device_kind": "NVIDIA H200"}, "paper_scale": part.data}
  (goal,) = [g for g in device.goals(data) if g[0].startswith("paper train step")]
  assert goal[1] is False and goal[2] == "1.500 s at batch 4 on NVIDIA H200; CPU-tuned path 14.000 s (9.33x)"
