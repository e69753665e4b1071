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
  assert parts["paper_scale"]["train"]["planned_peak_bytes"] > 0
  prof = parts["paper_scale"]["train"]["profile"]                 # the step's per-op profile
  assert "error" not in prof and prof["ops"] and prof["busy_ms"] <= prof["wall_ms"] * prof["lanes"]
  assert sum(c["share"] for c in prof["categories"].values()) == pytest.approx(1.0)
  assert "convolution" in prof["categories"]                       # the network's convolutions are there
  assert parts["scan_kernels"]["shapes"] and all("rows" in s for s in parts["scan_kernels"]["shapes"])
  assert "future mechanism study" in (out / device.LOG).read_text()

  results = tmp_path / "results" / "device.md"
  assert device.main(["--collect", str(out), "--results", str(results)]) == 0
  text = results.read_text()
  assert "Produced by `python -m benchmarks.device --tiny --out" in text and "- Machine: cpu" in text
  assert "- Commit: " in text and "(tiny CPU rehearsal)" in text
  assert "every correctness check passes: met (15 of 15 passed)" in text
  assert "### Where the train step's time goes" in text and "| category | ms a step | share of busy |" in text
  for goal in ("- paper-scale inference >= 30 frames/s on one H100 (batch 1): ",
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
