"""``experiments.xla_cache``: one persistent compilation cache for the commands, and its hit rate."""

import json
import os
import pathlib
import subprocess
import sys

import pytest

from experiments import xla_cache

ROOT = pathlib.Path(__file__).resolve().parents[1]

#: A command's shape: enable the cache, compile one program (numpy input: nothing else compiles), report.
COMPILE_ONCE = """
from experiments import xla_cache
xla_cache.enable()
import jax, numpy as np
jax.jit(lambda x: x * 3.0 + 1.0)(np.arange(4.0, dtype=np.float32)).block_until_ready()
print(xla_cache.summary())
"""


def _env(**extra):
  env = {k: v for k, v in os.environ.items()
         if not k.startswith(("NLOSJAX_", "JAX_COMPILATION_CACHE", "JAX_PERSISTENT_CACHE"))}
  return {**env, "JAX_PLATFORMS": "cpu", **extra}


def _run(env) -> str:
  proc = subprocess.run([sys.executable, "-c", COMPILE_ONCE], cwd=ROOT, env=env, capture_output=True,
                        text=True, timeout=300)
  assert proc.returncode == 0, proc.stderr
  return proc.stdout.strip().splitlines()[-1]


def test_a_second_process_reads_the_program_the_first_compiled(tmp_path):
  env = _env(NLOSJAX_CACHE_DIR=str(tmp_path / "xla"), NLOSJAX_CACHE_COUNTS=str(tmp_path))
  first, second = _run(env), _run(env)
  assert first == f"XLA compilation cache {tmp_path / 'xla'}: 0 of 1 compiles read from it (0%), 0 s of compiling saved"
  assert second.startswith(f"XLA compilation cache {tmp_path / 'xla'}: 1 of 1 compiles read from it (100%), ")
  assert any(p.name.endswith("-cache") for p in (tmp_path / "xla").iterdir())
  # Each process also left its counts for a command that runs it (NLOSJAX_CACHE_COUNTS).
  totals, processes = xla_cache.read_counts(tmp_path)
  assert processes == 2 and (totals["requests"], totals["hits"]) == (2, 1)


def test_switched_off_the_cache_reads_and_writes_nothing(tmp_path):
  line = _run(_env(NLOSJAX_CACHE_DIR=str(tmp_path / "xla"), NLOSJAX_CACHE="0"))
  assert line == "XLA compilation cache: off (NLOSJAX_CACHE=0)"
  assert not (tmp_path / "xla").exists()


def test_the_folder_is_the_clones_unless_the_environment_names_one(tmp_path):
  assert xla_cache.default_dir() == xla_cache.CLONE_DIR == ROOT / ".cache" / "xla"
  assert xla_cache.cache_dir({}) == str(ROOT / ".cache" / "xla")
  assert xla_cache.cache_dir({"JAX_COMPILATION_CACHE_DIR": "/a"}) == "/a"
  assert xla_cache.cache_dir({"JAX_COMPILATION_CACHE_DIR": "/a", "NLOSJAX_CACHE_DIR": "/b"}) == "/b"
  assert xla_cache.cache_dir({"NLOSJAX_CACHE_DIR": "/b", "NLOSJAX_CACHE": "0"}) is None
  environ = {"NLOSJAX_CACHE_DIR": str(tmp_path / "x"), "JAX_COMPILATION_CACHE_MAX_SIZE": "123"}
  assert xla_cache.configure(environ) == str(tmp_path / "x") and (tmp_path / "x").is_dir()
  assert environ["JAX_COMPILATION_CACHE_DIR"] == str(tmp_path / "x")
  assert environ["JAX_COMPILATION_CACHE_MAX_SIZE"] == "123"            # the user's setting is kept
  assert environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] == "0"


def test_without_filelock_the_cache_stays_off(tmp_path, monkeypatch):
  monkeypatch.setattr(xla_cache, "_have_filelock", lambda: False)
  environ = {"NLOSJAX_CACHE_DIR": str(tmp_path / "x")}
  assert xla_cache.configure(environ) is None and "JAX_COMPILATION_CACHE_DIR" not in environ
  assert "filelock" in xla_cache.summary()


def test_counts_are_written_whole_and_added_up(tmp_path):
  assert xla_cache.read_counts(tmp_path) == ({"requests": 0, "hits": 0, "saved_s": 0.0}, 0)
  path = xla_cache.write_counts(tmp_path)
  assert path == tmp_path / f"{os.getpid()}.json" and set(json.loads(path.read_text())) == {
      "requests", "hits", "saved_s"}
  (tmp_path / "9.json").write_text(json.dumps({"requests": 5, "hits": 2, "saved_s": 1.5}))
  (tmp_path / "10.json").write_text("{half a fi")                       # being written: skipped
  totals, processes = xla_cache.read_counts(tmp_path)
  assert processes == 2 and totals["requests"] >= 5 and totals["hits"] >= 2
  assert xla_cache.write_counts(tmp_path / "gone") is None
  assert xla_cache.summary({"requests": 0, "hits": 0, "saved_s": 0.0}, "/c") == (
      "XLA compilation cache /c: no compile went through it")


def test_the_main_job_ends_with_the_hit_rate(monkeypatch, capsys, tmp_path):
  from experiments import independent_set, main_job
  from experiments import train as cli
  monkeypatch.setattr(main_job, "train_and_evaluate", lambda config, workdir, **kw: print("trained"))
  monkeypatch.setattr(independent_set, "ensure_independent_set", lambda path, *a: path)
  cli.main(["--workdir", str(tmp_path / "run")])
  out = capsys.readouterr().out.strip().splitlines()
  assert out[-2] == "trained" and out[-1].startswith("XLA compilation cache"), out
  if os.environ.get("NLOSJAX_CACHE_DIR"):                # the suite's cache is the job's
    assert out[-1].startswith(f"XLA compilation cache {xla_cache._shown(os.environ['NLOSJAX_CACHE_DIR'])}: ")


def test_reconstruct_uses_the_same_cache_and_says_where_it_is(monkeypatch):
  from experiments import reconstruct
  monkeypatch.setattr(xla_cache, "enable", lambda: "/the/folder")
  assert reconstruct.enable_compilation_cache() == "/the/folder"
  text = " ".join(reconstruct.build_parser().format_help().split())
  assert ".cache/xla in a clone of the repository" in text and "else ~/.cache/nlosjax/xla" in text


def test_prune_drops_entries_unread_for_days_then_the_least_recently_read(tmp_path):
  day = 86400 * 10 ** 9
  now = 100 * day
  for key, read_days_ago in {"a": 0, "b": 1, "c": 2, "old": 8}.items():
    (tmp_path / f"{key}-cache").write_bytes(b"x")
    (tmp_path / f"{key}-atime").write_bytes((now - read_days_ago * day).to_bytes(8, "little"))
  (tmp_path / "noatime-cache").write_bytes(b"x")             # no read time: the file's own (today)
  (tmp_path / ".lockfile").write_bytes(b"")
  assert xla_cache.prune(tmp_path, max_entries=10, now_ns=now) == 1
  assert not (tmp_path / "old-cache").exists() and not (tmp_path / "old-atime").exists()
  assert xla_cache.prune(tmp_path, max_entries=10, now_ns=now) == 0
  assert xla_cache.prune(tmp_path, max_entries=2, now_ns=now) == 2
  assert sorted(p.name for p in tmp_path.glob("*-cache")) == ["a-cache", "noatime-cache"]
  assert xla_cache.prune(tmp_path / "missing") == 0


@pytest.mark.parametrize("command", ["train", "reconstruct", "evaluate", "make_dataset", "demo"])
def test_every_command_uses_the_cache_unless_given_no_cache(command, capsys, monkeypatch):
  """Each command's ``--help`` offers ``--no-cache`` with the one help text, and ``enable_unless``
  enables the cache only without it."""
  import importlib
  module = importlib.import_module(f"experiments.{command}")
  with pytest.raises(SystemExit) as e:
    module.main(["--help"])
  assert e.value.code == 0
  text = " ".join(capsys.readouterr().out.split())
  assert "--no-cache" in text and " ".join(xla_cache.NO_CACHE_HELP.split()) in text
  calls = []
  monkeypatch.setattr(xla_cache, "enable", lambda tidy=False: calls.append(tidy) or "/the/folder")
  assert xla_cache.enable_unless(True) is None and calls == []
  assert xla_cache.enable_unless(False, tidy=True) == "/the/folder" and calls == [True]
