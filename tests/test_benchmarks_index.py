"""``benchmarks/README.md`` is generated from the results files' headers and is up to date."""

import pytest

from benchmarks import index


def test_the_committed_index_is_what_the_results_files_say():
  assert index.INDEX.read_text() == index.render(), (
      "benchmarks/README.md is out of date: run python -m benchmarks.index")


def test_every_results_file_names_its_command_date_machine_and_commit():
  for e in index.entries():
    assert e.command.startswith("python -m "), e
    assert e.date[:4].isdigit() and e.machine != "?" and e.commit != "?", e


def test_a_header_is_read_as_written_and_a_file_without_a_command_is_refused(tmp_path):
  (tmp_path / "thing.md").write_text(
      "# A thing\n\n> **Still holds at abc1234** (checked)\n\n"
      "Produced by `python -m benchmarks.thing --fast`.\n\n- Date: 2026-01-02T03:04:05+00:00\n"
      "- Machine: Some CPU; 2 usable cores\n- Commit: 0123456789ab +changes\n")
  (tmp_path / "thing.json").write_text("{}")
  (tmp_path / "plain.md").write_text("# Plain\n\nProduced by `python -m p`.\n\n- Date: 2026-01-01\n"
                                     "- Machine: M\n- Commit: 1\n\nStill holds at default settings.\n")
  (tmp_path / "thing_more.md").write_text("# More\n\nProduced by `python -m x` on 2026-02-03 (5 s).\n"
                                          "- CPU: Other CPU; 4 cores\n")
  (tmp_path / "thing_more.png").write_bytes(b"")
  plain, a, b = index.entries(tmp_path)
  assert plain.still_holds == ""                  # prose in the body is not a banner
  assert a == index.Entry("thing", "A thing", "python -m benchmarks.thing --fast",
                          "2026-01-02T03:04:05+00:00", "Some CPU", "0123456789ab +changes", "abc1234")
  assert (b.date, b.machine, b.commit) == ("2026-02-03", "Other CPU", "?")
  assert index.companions(tmp_path, "thing") == ["thing.json"]       # thing_more.png is the other's
  assert index.companions(tmp_path, "thing_more") == ["thing_more.png"]
  (tmp_path / "bad.md").write_text("# No command\n")
  with pytest.raises(ValueError, match="Produced by"):
    index.entries(tmp_path)
