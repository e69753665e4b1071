"""The suite's own setup: a missing test requirement is named with the install command; the
persistent compilation cache and its hit rate; XLA flags."""

import importlib.metadata
import json
import os
import pathlib
import shutil
import subprocess
import sys

import pytest

import conftest


def _fake_metadata(monkeypatch, requires, installed):
  monkeypatch.setattr(importlib.metadata, "requires",
                      lambda dist: requires if dist == "nlosjax" else None)

  def version(dist):
    if dist not in installed:
      raise importlib.metadata.PackageNotFoundError(dist)
    return "1.0"
  monkeypatch.setattr(importlib.metadata, "version", version)


def test_only_the_test_extra_is_checked_and_missing_ones_are_named(monkeypatch):
  requires = ["jax>=0.10.2", 'pytest>=8; extra == "test"', "scikit-image>=0.24 ; extra == 'test'",
              'pytest-xdist>=3.6; extra == "test"', 'torch>=2.1; extra == "bench"']
  _fake_metadata(monkeypatch, requires, installed={"pytest"})
  assert conftest.missing_test_requirements() == ["scikit-image", "pytest-xdist"]
  _fake_metadata(monkeypatch, requires, installed={"pytest", "scikit-image", "pytest-xdist"})
  assert conftest.missing_test_requirements() == []


def test_uninstalled_package_says_how_to_install(monkeypatch):
  def absent(dist):
    raise importlib.metadata.PackageNotFoundError(dist)
  monkeypatch.setattr(importlib.metadata, "requires", absent)
  with pytest.raises(pytest.UsageError, match=r'pip install -e "\.\[test\]"'):
    conftest.missing_test_requirements()


def test_the_real_install_has_every_test_requirement():
  assert conftest.missing_test_requirements() == []


def test_the_suite_uses_the_clones_persistent_locked_cache_unless_switched_off(tmp_path):
  from experiments import xla_cache
  environ = {}
  path = conftest.shared_compilation_cache(environ)
  assert path == str(xla_cache.CLONE_DIR) == str(conftest_root() / ".cache" / "xla")
  assert environ["JAX_COMPILATION_CACHE_DIR"] == environ["NLOSJAX_CACHE_DIR"] == path
  assert environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] == conftest.SUITE_MIN_COMPILE_S
  kept = {"JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0"}         # the user's setting is kept
  conftest.shared_compilation_cache(kept)
  assert kept["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] == "0"
  assert int(environ["JAX_COMPILATION_CACHE_MAX_SIZE"]) > 0        # JAX locks the folder
  # git ignores it, so it is kept across runs and never committed.
  if (conftest_root() / ".git").exists() and shutil.which("git"):
    ignored = subprocess.run(["git", "check-ignore", "-q", path + "/entry-cache"], cwd=conftest_root())
    assert ignored.returncode == 0
  # NLOSJAX_CACHE_DIR (or a JAX_COMPILATION_CACHE_DIR already set) names another folder.
  given = {"NLOSJAX_CACHE_DIR": str(tmp_path / "mine")}
  assert conftest.shared_compilation_cache(given) == str(tmp_path / "mine")
  assert given["JAX_COMPILATION_CACHE_DIR"] == str(tmp_path / "mine") and (tmp_path / "mine").is_dir()
  jax_given = {"JAX_COMPILATION_CACHE_DIR": str(tmp_path)}
  assert conftest.shared_compilation_cache(jax_given) == str(tmp_path)
  # Switched off: for the suite, and then for every command a test runs too.
  off = {"NLOSJAX_TEST_CACHE": "0"}
  assert conftest.shared_compilation_cache(off) is None
  assert off == {"NLOSJAX_TEST_CACHE": "0", "NLOSJAX_CACHE": "0"}
  assert conftest.shared_compilation_cache({"NLOSJAX_CACHE": "0"}) is None


def conftest_root() -> pathlib.Path:
  return pathlib.Path(conftest.__file__).resolve().parent


def test_run_folders_of_killed_runs_are_removed_and_live_ones_kept(tmp_path):
  dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                        capture_output=True, text=True, check=True).stdout.strip()
  old = "nlosjax-test-xla-"              # the per-run cache folders of earlier versions
  for name, pid in ((conftest.RUN_PREFIX + "dead", dead), (conftest.RUN_PREFIX + "live", str(os.getpid())),
                    (conftest.RUN_PREFIX + "nopid", None), (old + "dead", dead)):
    folder = tmp_path / name
    folder.mkdir()
    if pid is not None:
      (folder / "pid").write_text(pid)
  (tmp_path / "unrelated").mkdir()
  removed = conftest.remove_stale_runs(str(tmp_path))
  assert sorted(pathlib.Path(p).name for p in removed) == sorted(
      [conftest.RUN_PREFIX + "dead", conftest.RUN_PREFIX + "nopid", old + "dead"])
  assert sorted(p.name for p in tmp_path.iterdir()) == [conftest.RUN_PREFIX + "live", "unrelated"]


def test_this_run_compiles_through_its_cache():
  import jax
  if os.environ.get("NLOSJAX_TEST_CACHE") == "0" or not os.environ.get("JAX_COMPILATION_CACHE_DIR"):
    pytest.skip("no compilation cache in this run")
  assert jax.config.jax_compilation_cache_dir == os.environ["JAX_COMPILATION_CACHE_DIR"]
  assert os.environ["NLOSJAX_CACHE_DIR"] == os.environ["JAX_COMPILATION_CACHE_DIR"]
  assert jax.config.jax_compilation_cache_max_size > 0
  assert os.path.isdir(os.environ["NLOSJAX_CACHE_COUNTS"])          # where this process's counts go


TINY_TEST = """
import jax, numpy as np
def test_compiles_one_program():
  jax.jit(lambda x: x * 3.0 + 1.0)(np.arange(4.0, dtype=np.float32)).block_until_ready()
"""


@pytest.mark.full
def test_the_suite_prints_the_hit_rate_over_its_workers(tmp_path):
  """This conftest (as a plugin) on a one-test module, twice, on 2 workers: the second run reads it back.

  The folder is shown relative to the working directory where it is inside it."""
  (tmp_path / "test_tiny.py").write_text(TINY_TEST)
  (tmp_path / "pytest.ini").write_text("[pytest]\n")
  env = {k: v for k, v in os.environ.items()
         if not k.startswith(("NLOSJAX_", "JAX_COMPILATION_CACHE", "JAX_PERSISTENT_CACHE", "PYTEST_"))}
  env.update(NLOSJAX_CACHE_DIR=str(tmp_path / "cache"), JAX_PLATFORMS="cpu", PYTHONPATH=str(conftest_root()),
             TMPDIR=str(tmp_path / "tmp"),
             JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")   # the tiny test's program is written too
  (tmp_path / "tmp").mkdir()
  cmd = [sys.executable, "-m", "pytest", "-q", "-p", "conftest", "-p", "no:cacheprovider", "-n", "2",
         "test_tiny.py"]
  lines = []
  for _ in range(2):
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    lines.append([l for l in proc.stdout.splitlines() if l.startswith("XLA compilation cache")])
  assert lines[0] == ["XLA compilation cache cache: 0 of 1 compiles read from it (0%), 0 s of compiling "
                      "saved, over 2 test processes"], lines
  assert lines[1][0].startswith("XLA compilation cache cache: 1 of 1 compiles read from it (100%), "), lines
  # The run's folder of counts is gone with it.
  assert not list((tmp_path / "tmp").glob(conftest.RUN_PREFIX + "*"))


class _Config:
  """What ``conftest.cache_summary`` reads of a pytest config."""

  def __init__(self, cache, counts):
    self._nlosjax_cache, self._nlosjax_counts = cache, counts


def test_the_summary_adds_up_the_processes_or_says_why_the_cache_is_off(tmp_path, monkeypatch):
  from experiments import xla_cache
  for pid, (requests, hits, saved) in {"11": (10, 4, 3.0), "12": (6, 6, 5.5)}.items():
    (tmp_path / f"{pid}.json").write_text(json.dumps({"requests": requests, "hits": hits, "saved_s": saved}))
  (tmp_path / "pid").write_text("1")                                  # not a count
  monkeypatch.setattr(xla_cache, "counts", lambda: {"requests": 0, "hits": 0, "saved_s": 0.0})
  assert conftest.cache_summary(_Config("/somewhere/xla", str(tmp_path))) == (
      "XLA compilation cache /somewhere/xla: 10 of 16 compiles read from it (62%), 8 s of compiling saved, "
      "over 2 test processes")
  monkeypatch.setenv("NLOSJAX_TEST_CACHE", "0")
  assert conftest.cache_summary(_Config(None, None)) == "XLA compilation cache: off (NLOSJAX_TEST_CACHE=0)"
  monkeypatch.delenv("NLOSJAX_TEST_CACHE")
  monkeypatch.setenv("NLOSJAX_CACHE", "0")
  assert conftest.cache_summary(_Config(None, None)) == "XLA compilation cache: off (NLOSJAX_CACHE=0)"
  assert conftest.cache_summary(object()) is None


def test_suite_xla_flags_are_added_once_and_only_where_known():
  known = lambda flag: True                                   # noqa: E731
  unknown = lambda flag: False                                # noqa: E731
  assert conftest.suite_xla_flags("", known) == "--xla_cpu_use_fusion_emitters=false"
  assert (conftest.suite_xla_flags("--xla_force_host_platform_device_count=4", known)
          == "--xla_force_host_platform_device_count=4 --xla_cpu_use_fusion_emitters=false")
  # The user's own setting wins; a jaxlib that does not know the flag does not get it.
  assert conftest.suite_xla_flags("--xla_cpu_use_fusion_emitters=true", known) == \
      "--xla_cpu_use_fusion_emitters=true"
  assert conftest.suite_xla_flags("", unknown) == ""
  assert not conftest._xla_flag_known("--xla_no_such_flag_for_nlosjax=1")


def test_the_tests_that_build_most_programs_are_named_over_every_process(tmp_path, monkeypatch):
  import jax
  import numpy as np
  (tmp_path / "1.compiles").write_text(json.dumps({"a::t1": [300, 9.0], "a::t2": [3, 0.5]}))
  (tmp_path / "2.compiles").write_text(json.dumps({"b::t3": [40, 2.0]}))

  class Config:
    _nlosjax_counts = str(tmp_path)
  monkeypatch.setattr(conftest, "_COMPILES", {})
  lines = conftest.most_compiles(Config(), n=2)
  assert lines[0].startswith("XLA programs built") and "343 in 3 tests, 12 s" in lines[0]
  assert "a::t1" in lines[1] and "b::t3" in lines[2] and len(lines) == 3
  # This process's listener counts a program under the test that built it, and only then.
  monkeypatch.setattr(conftest, "_CURRENT", ["here"])
  jax.jit(lambda x: x * 3.0 + 1.0)(np.arange(7.0, dtype=np.float32))   # one program no other test builds
  monkeypatch.setattr(conftest, "_CURRENT", [None])
  jax.jit(lambda x: x * 5.0 - 2.0)(np.arange(9.0, dtype=np.float32))
  if not conftest._COMPILES:
    pytest.skip("the listener is registered where the compilation cache is on")
  assert conftest._COMPILES["here"][0] == 1
