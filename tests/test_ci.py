"""``.ci/main_job``: CI fails on a main job that fails, hangs or writes no table, never on a slow one.

Each case runs the real script in a scratch copy of ``.ci/`` with a stand-in ``python`` on
``PATH`` whose ``-m experiments.train`` sleeps, fails or writes the table as told.
"""

import os
import pathlib
import shutil
import subprocess
import sys

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


# Stand-ins for what `.ci/run` calls: `python3 -m venv` makes an empty environment (other `python3`
# calls, such as the CPU line's, go to the real interpreter), `pip` does nothing, `ruff` exits
# $FAKE_LINT, `python -m pytest -q` sleeps 1 s and exits $FAKE_SUITE ($FAKE_FULL with `--tier full`), and
# the main job sleeps 1 s.
FAKES = {
    "python3": '#!/usr/bin/env bash\nif [[ "$1 $2" == "-m venv" ]]; then mkdir -p "${@: -1}/bin"; '
               'touch "${@: -1}/bin/activate"; exit 0; fi\nexec "$REAL_PYTHON" "$@"\n',
    "python": '#!/usr/bin/env bash\nif [[ "$1" == --version ]]; then echo "Python 3.x"; exit 0; fi\n'
              'sleep 1; if [[ "$*" == *"--tier full"* ]]; then exit "${FAKE_FULL:-0}"; fi; exit "${FAKE_SUITE:-0}"\n',
    "pip": "#!/usr/bin/env bash\nexit 0\n",
    "ruff": '#!/usr/bin/env bash\nexit "${FAKE_LINT:-0}"\n',
}


def run_ci(tmp_path, **fake):
  (tmp_path / ".ci").mkdir()
  shutil.copy(ROOT / ".ci" / "run", tmp_path / ".ci" / "run")
  (tmp_path / ".ci" / "main_job").write_text("sleep 1\n")
  (tmp_path / "experiments").mkdir()                         # the CPU line's helper, as in a clone
  (tmp_path / "experiments" / "__init__.py").write_text("")
  shutil.copy(ROOT / "experiments" / "provenance.py", tmp_path / "experiments" / "provenance.py")
  bin_dir = tmp_path / "bin"
  bin_dir.mkdir()
  for name, text in FAKES.items():
    (bin_dir / name).write_text(text)
    (bin_dir / name).chmod(0o755)
  env = {k: v for k, v in os.environ.items() if k not in ("NLOSJAX_VENV", "CI", "NLOSJAX_MAIN_JOB")}
  env.update(PATH=f"{bin_dir}:{os.environ['PATH']}", REAL_PYTHON=sys.executable, NLOSJAX_MAIN_JOB="1",
             **{f"FAKE_{k.upper()}": str(v) for k, v in fake.items()})
  return subprocess.run(["bash", str(tmp_path / ".ci" / "run")], env=env, capture_output=True, text=True,
                        timeout=120)


def _phases(stdout: str) -> dict[str, int]:
  table = stdout.split("== CI phases (seconds):\n", 1)[1].split("\n== CPU: ", 1)[0]
  return {line[:31].strip(): int(line[31:]) for line in table.splitlines()}


def test_ci_ends_with_each_phases_seconds_and_the_cpus_model_clock_and_cache(tmp_path):
  from experiments.provenance import cpu_facts
  proc = run_ci(tmp_path)
  assert proc.returncode == 0, proc.stdout + proc.stderr
  phases = _phases(proc.stdout)
  assert list(phases) == ["venv + install", "lint", "suite", "suite (full tier)", "main-job install", "main job",
                          "total"]
  assert phases["suite"] >= 1 and phases["suite (full tier)"] >= 1 and phases["main job"] >= 1
  assert phases["total"] >= 3
  # The last line: "== CPU: AMD EPYC, 2596 MHz, cache 1024 KB; 2 cores" (the clock as read: it may move).
  last, facts = proc.stdout.rstrip().splitlines()[-1], cpu_facts()
  assert last.startswith(f"== CPU: {facts['model']}") and last.endswith(f"; {len(os.sched_getaffinity(0))} cores")
  assert (" MHz" in last) == bool(facts["mhz"]) and (f"cache {facts['cache']}" in last) == bool(facts["cache"])


@pytest.mark.parametrize("fake, failed, after", [({"lint": 1}, "lint", "suite"), ({"suite": 3}, "suite", "main job"),
                                                 ({"full": 4}, "suite (full tier)", "main job")])
def test_a_failing_phase_still_fails_ci_after_the_table(tmp_path, fake, failed, after):
  proc = run_ci(tmp_path, **fake)
  assert proc.returncode == list(fake.values())[0]
  phases = _phases(proc.stdout)
  assert f"{failed} (FAILED)" in phases and after not in phases and "total" in phases
  assert "\n== CPU: " in proc.stdout
