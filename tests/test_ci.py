"""``.ci/main_job``: CI fails on a main job that fails, hangs or writes no table, never on a slow one.

Each case runs the real script in a scratch copy of ``.ci/`` with a stand-in ``python`` on
``PATH`` whose ``-m experiments.train`` sleeps, fails or writes the table as told.
"""

import os
import pathlib
import shutil
import subprocess

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]

FAKE_PYTHON = """#!/usr/bin/env bash
# stand-in for `python -m experiments.train`: $FAKE_SLEEP seconds, then $FAKE_TABLE, then $FAKE_EXIT
sleep "${FAKE_SLEEP:-0}"
if [[ "${FAKE_TABLE:-1}" == 1 ]]; then mkdir -p runs/default/results && echo '{}' > runs/default/results/table.json; fi
exit "${FAKE_EXIT:-0}"
"""


def run_main_job(tmp_path, hang_s, **fake):
  (tmp_path / ".ci").mkdir()
  shutil.copy(ROOT / ".ci" / "main_job", tmp_path / ".ci" / "main_job")
  bin_dir = tmp_path / "bin"
  bin_dir.mkdir()
  (bin_dir / "python").write_text(FAKE_PYTHON)
  (bin_dir / "python").chmod(0o755)
  env = {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}", "NLOSJAX_HANG_S": str(hang_s),
         **{f"FAKE_{k.upper()}": str(v) for k, v in fake.items()}}
  return subprocess.run(["bash", str(tmp_path / ".ci" / "main_job")], env=env, capture_output=True, text=True,
                        timeout=60)


def test_a_slow_main_job_passes_and_prints_its_time(tmp_path):
  proc = run_main_job(tmp_path, hang_s=20, sleep=2)
  assert proc.returncode == 0, proc.stderr
  assert "== main job: " in proc.stdout and "within its budget" in proc.stdout
  # Past its budget (the script's 1200 s shrunk to 1 s, so a 2 s job stands for a 25-minute one).
  script = tmp_path / ".ci" / "main_job"
  assert "budget_s=1200" in script.read_text()
  script.write_text(script.read_text().replace("budget_s=1200", "budget_s=1"))
  shutil.rmtree(tmp_path / "runs")
  env = {**os.environ, "PATH": f"{tmp_path / 'bin'}:{os.environ['PATH']}", "NLOSJAX_HANG_S": "20", "FAKE_SLEEP": "2"}
  proc = subprocess.run(["bash", str(script)], env=env, capture_output=True, text=True, timeout=60)
  assert proc.returncode == 0, proc.stderr
  assert "over (not a CI failure" in proc.stdout


@pytest.mark.parametrize("fake, message", [
    ({"sleep": 30}, "still running after 2 s"),                # a hang
    ({"exit": 3}, "exited with status 3"),                     # a failure
    ({"table": 0}, "wrote no runs/default/results/table.json"),  # no table
])
def test_a_hung_failed_or_tableless_main_job_fails_ci(tmp_path, fake, message):
  proc = run_main_job(tmp_path, hang_s=2, **fake)
  assert proc.returncode == 1
  assert message in proc.stderr
