"""benchmarks.reconstruct_time: the report from cold-run timings (the runs themselves faked)."""

from benchmarks import reconstruct_time as R


def test_report_gives_ratios_to_lct_and_the_goal_verdict(tmp_path, monkeypatch):
  walls = {"ours": 12.0, "ours_s": 8.0, "lct": 4.0, "phasor": 3.0, "rsd": 2.0}
  calls = []

  def fake(capture, method, pretrained, out):
    calls.append((method, pretrained))
    wall = walls[method] * (1.5 if pretrained == "real" else 1.0) + len(calls) * 0.01
    return {"wall_s": wall, "timings": {"reconstruct_s": walls[method] / 2}, "shape": (512, 64, 64)}

  monkeypatch.setattr(R, "time_one", fake)
  out = tmp_path / "r.md"
  assert R.main(["--repeats", "2", "--out", str(out)]) == 0
  assert calls[:7] == [("ours", "real"), ("ours_s", "real"), ("ours", "cpu"), ("ours_s", "cpu"),
                       ("lct", None), ("phasor", None), ("rsd", None)]
  assert len(calls) == 14                                   # interleaved: each method twice
  text = out.read_text()
  assert "Produced by `python -m benchmarks.reconstruct_time`" in text and "(512, 64, 64)" in text
  ours = next(x for x in text.splitlines() if x.startswith("| ours | cpu |"))
  # best wall 12.03 s (first round), LCT's 4.05 s: ratio 2.97; over the 10 s goal.
  assert "| 12.03 | 6.00 | 2.97 | no |" in ours
  assert next(x for x in text.splitlines() if x.startswith("| ours_s | cpu |")).endswith("| yes |")
  # real's Ours: 18.01 s; its Ours-S 12.02 s: over the goal.
  assert "| 18.01 | 6.00 | 4.45 | no |" in next(x for x in text.splitlines() if x.startswith("| ours | real |"))
  assert next(x for x in text.splitlines() if x.startswith("| ours_s | real |")).endswith("| no |")
