"""experiments.studies.stopping_replay: candidate stopping rules replayed exactly on recorded validation curves."""

import pathlib

import numpy as np

from experiments.studies import stopping_replay as S

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _points(vals, val_s=1.0, step_s=10.0):
  """Curve points every 50 steps: (step, val, time_s, val_s) with 50 steps = step_s s plus each validation."""
  return [(50 * (i + 1), v, (i + 1) * (step_s + val_s), val_s) for i, v in enumerate(vals)]


def test_a_hand_worked_curve():
  #          50   100  150  200   250   300  350  400
  vals = [10.0, 12.0, 11.0, 11.5, 12.04, 11.0, 13.0, 11.0]
  # patience 2: after 150, 200 nothing beats 12.0 + 0.05 -> stops at 200, best 12.0 at 100
  got = S.replay(_points(vals), 50, 2)
  assert (got["step"], got["best"], got["best_step"], got["validations"]) == (200, 12.0, 100, 4)
  assert got["time_s"] == 4 * 11.0
  # patience 4: at 300 the last four (11, 11.5, 12.04, 11) gain nothing over 12.0 + 0.05: it stops
  # there, keeping the best it saw (12.04 at 250), before 13.0 at 350
  got = S.replay(_points(vals), 50, 4)
  assert (got["step"], got["best"], got["best_step"]) == (300, 12.04, 250)
  # patience 5: 13.0 at 350 is a gain; the curve ends before a stop
  assert S.replay(_points(vals), 50, 5) is None
  # every 100, patience 1: validations 12.0 (100), 11.5 (200) -> stops at 200; the skipped
  # validations at 50 and 150 are not paid for
  got = S.replay(_points(vals), 100, 1)
  assert (got["step"], got["best"], got["validations"]) == (200, 12.0, 2)
  assert got["time_s"] == 4 * 11.0 - 2 * 1.0


def test_the_recorded_rule_replayed_stops_every_kept_run_where_it_stopped():
  """The replay is exact: the rule the runs trained with, replayed, gives each recorded stop and best."""
  runs = S.curves()
  plateau = {k: r for k, r in runs.items() if r["stop_reason"] == "plateau"}
  assert len(plateau) >= 40
  for name, run in plateau.items():
    got, ref = S.replay(run["points"], *S.RECORDED), S.recorded(run)
    assert got is not None, name
    assert (got["step"], got["best"], got["best_step"]) == (ref["step"], ref["best"], ref["best_step"]), name


def test_compare_reports_the_mean_change_with_an_interval_that_holds_it():
  runs = {f"r{i}": {"points": _points(v), "rule": {"every": 50, "patience": 4}, "stop_reason": "plateau"}
          for i, v in enumerate([[10, 11, 11, 11, 11, 11], [10, 10, 10.5, 10, 10, 10, 10]])}
  rows = {(r["every"], r["patience"]): r for r in S.compare(runs)}
  r = rows[(50, 1)]        # run 0 stops at 150 (best 11), run 1 at 100 (best 10, not 10.5)
  assert np.isclose(r["val_change_db"], np.mean([0.0, -0.5]))
  assert r["time_ratio_ci95"][0] <= r["time_ratio"] <= r["time_ratio_ci95"][1]
  assert r["same_best"] == 1 and r["lost_over_0p1db"] == 1
