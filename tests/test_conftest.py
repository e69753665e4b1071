"""The suite's own setup: a missing test requirement is named with the install command."""

import importlib.metadata
import os
import shutil

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


def test_the_compilation_cache_is_a_fresh_folder_unless_switched_off_or_given(tmp_path):
  environ = {}
  path = conftest.shared_compilation_cache(environ)
  try:
    assert environ["JAX_COMPILATION_CACHE_DIR"] == environ["NLOSJAX_CACHE_DIR"] == path
    assert environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] == "0"
    assert not any(os.scandir(path))          # nothing from an earlier run
  finally:
    shutil.rmtree(path)
  assert conftest.shared_compilation_cache({"NLOSJAX_TEST_CACHE": "0"}) is None
  given = {"JAX_COMPILATION_CACHE_DIR": str(tmp_path)}
  assert conftest.shared_compilation_cache(given) is None
  assert given == {"JAX_COMPILATION_CACHE_DIR": str(tmp_path)}


def test_this_run_compiles_through_the_shared_cache():
  import jax
  if os.environ.get("NLOSJAX_TEST_CACHE") == "0":
    pytest.skip("switched off for this run")
  assert jax.config.jax_compilation_cache_dir == os.environ["JAX_COMPILATION_CACHE_DIR"]
  assert jax.config.jax_persistent_cache_min_compile_time_secs == 0
