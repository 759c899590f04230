"""Rosenthal study (see torchsph/post/rosenthal.py): SPH T_L isotherm of a beam moving over a
thick steel plate, against Rosenthal's point source and its Gaussian-spot superposition.

    python scripts/studies/rosenthal.py [--dx-mm 0.25] [--t-end 0.6] [--power 800] [--radius-mm 0.5]
                                [--plate-mm 24 12 6] [--x-start-mm -8] [--compile]

Rosenthal's solution is for a semi-infinite body: the plate must be several diffusion
lengths sqrt(alpha t) larger than the isotherm on every side, and t long enough for the
isotherm to stop growing (check by running two end times).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from torchsph.post.rosenthal import run_study  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--dx-mm", type=float, default=0.25)
    ap.add_argument("--t-end", type=float, default=0.6)
    ap.add_argument("--power", type=float, default=800.0)
    ap.add_argument("--speed", type=float, default=0.015)
    ap.add_argument("--radius-mm", type=float, default=0.5)
    ap.add_argument("--plate-mm", type=float, nargs=3, default=[24.0, 12.0, 6.0])
    ap.add_argument("--x-start-mm", type=float, default=-8.0)
    ap.add_argument("--compile", action="store_true")
    a = ap.parse_args()
    L_, W_, D_ = (v * 1e-3 for v in a.plate_mm)
    r = run_study(a.dx_mm * 1e-3, a.t_end, a.power, a.speed, a.radius_mm * 1e-3, a.compile,
                  x_start=a.x_start_mm * 1e-3, length=L_, width=W_, depth=D_)
    L, W = r["sph"]
    print(f"dx = {a.dx_mm} mm, Q = {a.power} W, v = {a.speed * 1e3:g} mm/s, r = {a.radius_mm} mm, t = {a.t_end} s: "
          f"N = {r['n']}, steps = {r['steps']}, wall {r['wall_s']:.1f} s")
    print(f"T_L isotherm on the top layer: SPH length {L * 1e3:.3f} mm, width {W * 1e3:.3f} mm")
    for name in ("gaussian", "point"):
        Lr, Wr = r[name]
        print(f"  Rosenthal ({name}): length {Lr * 1e3:.3f} mm ({(L / Lr - 1) * 100:+.1f} %), "
              f"width {Wr * 1e3:.3f} mm ({(W / Wr - 1) * 100:+.1f} %)")


if __name__ == "__main__":
    main()
