"""Write tests/data/mitransient_patch.npz: a small confocal mitransient render of one planar patch.

Run once, in an environment with nlosjax and its ``render`` extra (mitsuba,
mitransient) and Debian's ``libllvm19``, from the repository root:

  DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM-19.so \\
    python -m tests.data.make_mitransient_fixture

The file keeps mitransient's raw ``(H, W, T)`` output (colour channels
averaged, divided by its maximum ``scale`` and kept as float16 to stay a few KB) and the versions that made it;
tests/test_mitransient.py converts it with
:func:`nlosjax.data.scenes.mitransient.to_transient` and compares it with our
own renderer, so the suite needs no mitsuba.
"""

import pathlib

import numpy as np

from nlosjax.data.scenes import mitransient as mt
from nlosjax.physics import Setup

OUT = pathlib.Path(__file__).parent / "mitransient_patch.npz"
SETUP = Setup(wall_size=1.0, grid=(12, 12), bin_width=0.02 / 299_792_458.0, num_bins=96)
# A tilted patch off the wall's centre in x and y, so a flip of either axis or of time shows.
PATCH = mt.Patch(centre=(0.15, -0.1, 0.5), half_size=(0.12, 0.08),
                 axes=((np.cos(0.3), 0.0, np.sin(0.3)), (0.0, 1.0, 0.0)), albedo=0.8)
SAMPLES_PER_POINT = 65536


def main():
  raw, seconds = mt.render_raw([PATCH], SETUP, samples_per_point=SAMPLES_PER_POINT)
  import mitransient  # imported after render_raw has set a Mitsuba variant, as mitransient requires
  import mitsuba

  raw = raw.mean(-1)
  scale = float(raw.max())
  np.savez_compressed(OUT, raw=(raw / scale).astype(np.float16), scale=scale,
                      mitsuba=mitsuba.__version__, mitransient=mitransient.__version__,
                      samples_per_point=SAMPLES_PER_POINT, seconds=seconds)
  print(f"wrote {OUT} ({OUT.stat().st_size} bytes); render {seconds:.2f} s, "
        f"mitsuba {mitsuba.__version__}, mitransient {mitransient.__version__}")


if __name__ == "__main__":
  main()
