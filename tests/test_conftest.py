"""The suite's own setup: a missing test requirement is named with the install command."""

import importlib.metadata
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


def test_the_compilation_cache_is_a_fresh_locked_folder_unless_switched_off_or_given(tmp_path):
  environ = {}
  path = conftest.shared_compilation_cache(environ)
  try:
    assert environ["JAX_COMPILATION_CACHE_DIR"] == environ["NLOSJAX_CACHE_DIR"] == path
    assert environ["NLOSJAX_TEST_CACHE_DIR"] == path
    assert environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] == "0"
    assert int(environ["JAX_COMPILATION_CACHE_MAX_SIZE"]) > 0        # JAX locks the folder
    assert [e.name for e in os.scandir(path)] == ["pid"]              # nothing from an earlier run
  finally:
    shutil.rmtree(path)
  assert conftest.shared_compilation_cache({"NLOSJAX_TEST_CACHE": "0"}) is None
  given = {"JAX_COMPILATION_CACHE_DIR": str(tmp_path)}
  assert conftest.shared_compilation_cache(given) is None
  assert given == {"JAX_COMPILATION_CACHE_DIR": str(tmp_path)}


def test_folders_of_killed_runs_are_removed_and_live_ones_kept(tmp_path):
  dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                        capture_output=True, text=True, check=True).stdout.strip()
  for name, pid in (("dead", dead), ("live", str(os.getpid())), ("nopid", None)):
    folder = tmp_path / (conftest.CACHE_PREFIX + name)
    folder.mkdir()
    if pid is not None:
      (folder / "pid").write_text(pid)
  (tmp_path / "unrelated").mkdir()
  removed = conftest.remove_stale_caches(str(tmp_path))
  assert sorted(pathlib.Path(p).name for p in removed) == [conftest.CACHE_PREFIX + "dead",
                                                           conftest.CACHE_PREFIX + "nopid"]
  assert sorted(p.name for p in tmp_path.iterdir()) == [conftest.CACHE_PREFIX + "live", "unrelated"]


def test_this_run_compiles_through_its_cache():
  import jax
  if os.environ.get("NLOSJAX_TEST_CACHE") == "0" or not os.environ.get("JAX_COMPILATION_CACHE_DIR"):
    pytest.skip("no compilation cache in this run")
  assert jax.config.jax_compilation_cache_dir == os.environ["JAX_COMPILATION_CACHE_DIR"]
  if os.environ.get("NLOSJAX_TEST_CACHE_DIR") == os.environ["JAX_COMPILATION_CACHE_DIR"]:
    assert jax.config.jax_persistent_cache_min_compile_time_secs == 0     # made by conftest
    assert jax.config.jax_compilation_cache_max_size > 0


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
