"""The machine the study ran on: one line of hardware and versions, and the load average."""

from __future__ import annotations

from experiments import provenance as _machine_facts


def machine_line() -> str:
  return f"{_machine_facts.machine_text()}; {_machine_facts.versions_text()}"


def load_average() -> str:
  return _machine_facts.load_average(", ")
