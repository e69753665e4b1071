"""benchmarks.reconstruct_time: the report from cold and warm timings (the runs themselves faked)."""

import pathlib

from benchmarks import reconstruct_time as R


def _fake_runs(monkeypatch, walls, calls, *, old_factor=2.0):
  def pair(capture, method, pretrained, out, code):
    calls.append((method, pretrained, code == R.ROOT))
    factor = (1.5 if pretrained == "real" else 1.0) * (1.0 if code == R.ROOT else old_factor)
    cold = walls[method] * factor + len(calls) * 0.01
    return {"cold_s": cold, "warm_s": cold / 3, "reconstruct_cold_s": walls[method] / 2,
            "reconstruct_warm_s": walls[method] / 4, "shape": (512, 64, 64)}

  monkeypatch.setattr(R, "time_pair", pair)
  monkeypatch.setattr(R, "time_help", lambda code: 0.5 if code == R.ROOT else 1.5)


def test_report_gives_cold_and_warm_walls_ratios_to_lct_and_the_goal_verdicts(tmp_path, monkeypatch):
  walls = {"ours": 12.0, "ours_s": 8.0, "lct": 4.0, "phasor": 3.0, "rsd": 2.0}
  calls = []
  _fake_runs(monkeypatch, walls, calls)
  out = tmp_path / "r.md"
  assert R.main(["--repeats", "2", "--out", str(out)]) == 0
  assert [c[:2] for c in calls[:7]] == [("ours", "real"), ("ours_s", "real"), ("ours", "cpu"),
                                        ("ours_s", "cpu"), ("lct", None), ("phasor", None),
                                        ("rsd", None)]
  assert len(calls) == 14                                   # interleaved: each method twice
  text = out.read_text()
  assert "Produced by `python -m benchmarks.reconstruct_time`" in text and "(512, 64, 64)" in text
  row = lambda prefix: next(x for x in text.splitlines() if x.startswith(prefix))
  # Ours (cpu): best cold 12.03 s (first round; the second is 12.10), warm a third of it
  # (4.01 s); LCT's best cold 4.05 s: ratio 2.97; over the 10 s goal, over the 4 s one.
  assert row("| ours | cpu | this commit |").endswith(
      "| 12.03, 12.10 | 4.01, 4.03 | 12.03 | 4.01 | 6.00 / 3.00 | 2.97 | no | no |")
  assert row("| ours_s | cpu |").endswith("| yes | yes |")     # 8.04 cold, 2.68 warm
  assert row("| ours | real |").endswith("| 4.45 | no | no |")  # 18.01 / 4.05
  assert "this commit 0.50 s (under 1 s)" in text
  assert "--baseline" not in text and "this /" not in text


def test_baseline_runs_the_learned_methods_on_the_old_commit_side_by_side(tmp_path, monkeypatch):
  walls = {"ours": 12.0, "ours_s": 8.0, "lct": 4.0, "phasor": 3.0, "rsd": 2.0}
  calls = []
  _fake_runs(monkeypatch, walls, calls)
  made = []

  def worktree(rev, where):
    made.append(rev)
    path = pathlib.Path(where) / "baseline"
    path.mkdir()
    return path, "abc123def456"

  monkeypatch.setattr(R, "_worktree", worktree)
  monkeypatch.setattr(R, "_remove_worktree", lambda path: made.append(("removed", path.name)))
  out = tmp_path / "r.md"
  assert R.main(["--repeats", "1", "--pretrained", "cpu", "--baseline", "HEAD~1", "--out", str(out)]) == 0
  assert made == ["HEAD~1", ("removed", "baseline")]
  old = [c[:2] for c in calls if not c[2]]
  assert old == [("ours", "cpu"), ("ours_s", "cpu")]                # classic methods run once
  text = out.read_text()
  assert "--baseline HEAD~1" in text and "`abc123def456` 1.50 s (over 1 s)" in text
  assert "| ours | cpu | `abc123def456` |" in text
  # Old code twice as slow: this / old = 0.50 cold and warm (up to the fake's 0.01 s steps).
  ratio = next(x for x in text.splitlines() if x.startswith("- ours (cpu)"))
  assert "cold this / `abc123def456` = 0.5" in ratio and "warm 0.5" in ratio
