"""``python -m tests.golden [FAMILY ...] [--check] [--since REV] [--isa-check]``: regenerate the golden arrays.

Runs each family's probe (all of them by default) in the suite's XLA settings, prints per
family how far each key moved from its committed golden (and the closest call: the key
whose difference is the largest share of its tolerance), and writes the new arrays of the
families that moved (``--check``: writes nothing, exits 1 if anything moved beyond its
tolerance). Then lists the results files whose command imports a module changed since
``--since`` (default ``HEAD``: the uncommitted changes): the files this change can move,
to be regenerated with it.

``--isa-check`` measures the tolerances' margin against what another CPU does: it reruns the
families with XLA and NumPy held to narrower vector units (AVX2, SSE4.2; our machines differ
in AVX-512) and with XLA's optimisations on, and prints each family's closest call; nothing
is written.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

#: Environments that round otherwise, as another CPU model or build would (``--isa-check``).
VARIATIONS = {
    "avx2": {"XLA_FLAGS+": "--xla_cpu_max_isa=AVX2", "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR"},
    "sse4.2": {"XLA_FLAGS+": "--xla_cpu_max_isa=SSE4_2",
               "NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR"},
    "xla-optimised": {"JAX_DISABLE_MOST_OPTIMIZATIONS": "0"},
}


def run(families, *, write: bool) -> int:
  """Probe, compare, print; write the families that moved where ``write``. Returns how many moved."""
  from tests import golden
  from tests.golden import probes
  moved = 0
  for family in families:
    t0 = time.perf_counter()
    new = probes.FAMILIES[family][0]()
    old = golden.load(family)
    bad = golden.compare(family, new, old)
    closest = golden.closest_call(family, new, old)
    state = "unchanged" if not bad else f"{len(bad)} of {len(set(new) | set(old))} keys moved"
    print(f"{family}: {len(new)} arrays, {time.perf_counter() - t0:.1f} s, {state}; closest call {closest}",
          flush=True)
    for line in bad:
      print(f"  {line}")
    moved += bool(bad)
    if write and bad:
      print(f"  wrote {golden.save(family, new)}")
  return moved


def isa_check(families) -> None:
  """Rerun ``families`` under each of :data:`VARIATIONS` in a subprocess; print their closest calls."""
  for name, settings in VARIATIONS.items():
    env = dict(os.environ)
    for key, value in settings.items():
      if key.endswith("+"):
        env[key[:-1]] = f"{env.get(key[:-1], '')} {value}".strip()
      else:
        env[key] = value
    print(f"== {name}: {settings}", flush=True)
    subprocess.run([sys.executable, "-m", "tests.golden", "--check", "--no-touched", *families], env=env)


def main(argv=None) -> int:
  from tests import golden
  golden.suite_environment(os.environ)
  from tests.golden import probes
  p = argparse.ArgumentParser(prog="python -m tests.golden", description=__doc__.split("\n\n")[0])
  p.add_argument("families", nargs="*", metavar="FAMILY",
                 help=f"families to run (default all): {', '.join(probes.FAMILIES)}")
  p.add_argument("--check", action="store_true", help="compare only; write nothing; exit 1 on a difference")
  p.add_argument("--since", default="HEAD", help="list the results files a change since REV can move (default HEAD)")
  p.add_argument("--no-touched", action="store_true", help="do not list the results files")
  p.add_argument("--isa-check", action="store_true",
                 help="rerun under narrower vector units and XLA's optimisations; print the margins; write nothing")
  args = p.parse_args(argv)
  unknown = sorted(set(args.families) - set(probes.FAMILIES))
  if unknown:
    p.error(f"unknown family {', '.join(unknown)}; known: {', '.join(probes.FAMILIES)}")
  families = args.families or list(probes.FAMILIES)
  if args.isa_check:
    isa_check(families)
    return 0
  moved = run(families, write=not args.check)
  if not args.no_touched:
    from benchmarks import index
    touched = index.touched(args.since)
    print(f"results files a change since {args.since} can move (their command imports a changed module): "
          + (", ".join(touched) if touched else "none"))
  return 1 if (args.check and moved) else 0


if __name__ == "__main__":
  sys.exit(main())
