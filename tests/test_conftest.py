"""The suite's own setup: a missing test requirement is named with the install command."""

import importlib.metadata

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
