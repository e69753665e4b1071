"""The machine the study ran on: one line of hardware and versions, and the load average."""

from __future__ import annotations

from experiments import provenance as _machine_facts


def machine_line() -> str:
  from benchmarks.model import machine
  m = machine()
  return (f"{m['cpu']}; {m['cores']} usable cores; {m['mem_gib']:.1f} GiB; JAX backend"
          f" {m['backend']} ({m['device']}); {m['versions']}")


def load_average() -> str:
  return _machine_facts.load_average(", ")
