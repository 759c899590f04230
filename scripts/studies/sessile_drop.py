"""Wetting (SPEC 3b): caps on a plate settle at the contact angle they are given.

Runs ``cases/sessile_drop_2d`` or ``cases/sessile_drop_3d`` for each theta_eq, started
``--offset`` degrees off it (below 90 deg from above: the cap spreads; from 90 deg up from
below: it draws in), and prints the fitted angle averaged over 14-20 ms (the settling drag
ends at 10 ms), its spread, the largest centre-of-mass speed over sigma / eta, particles and
wall time: the README's table.

    python scripts/studies/sessile_drop.py --dim 2                    # ~5 min
    python scripts/studies/sessile_drop.py --dim 3 --angles 60 90 120 # ~15 min
    python scripts/studies/sessile_drop.py --dim 2 --angles 60 --set scene.dx_m=2.5e-5
    python scripts/studies/sessile_drop.py --dim 3 --angles 120 --set scene.dx_m=3.125e-5 \
        --checkpoint-dir runs/sessile_r16   # hours: run it again to continue after a stop
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from torchsph.post.caps import settle  # noqa: E402
from torchsph.io.config import load_case  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dim", type=int, choices=(2, 3), default=2)
    ap.add_argument("--angles", type=float, nargs="+", default=[30.0, 60.0, 90.0, 120.0], help="theta_eq (deg)")
    ap.add_argument("--offset", type=float, default=15.0, help="start this far off theta_eq (deg)")
    ap.add_argument("--set", action="append", default=[], help="case overrides, section.key=value")
    ap.add_argument("--checkpoint-dir", type=Path, default=None,
                    help="checkpoint each cap here every ms of process (theta_NNN.pt) and continue from it")
    a = ap.parse_args()
    if a.checkpoint_dir is not None:
        a.checkpoint_dir.mkdir(parents=True, exist_ok=True)
    case = ROOT / "cases" / f"sessile_drop_{a.dim}d"
    print("| theta_eq | started at | R, dx | settled (mean, 14-20 ms) | spread | max speed / (sigma/eta) | particles | wall |")
    print("|---|---|---|---|---|---|---|---|")
    for th in a.angles:
        start = th + a.offset if th < 90 else th - a.offset
        over = [f"surface.contact_angle_deg={th}", f"scene.initial_angle_deg={start}"]
        if a.dim == 2:  # the verified 2-D set-up (tests/test_wetting.py): dx = R/15, the 30 deg cap R = 30 dx
            over += ["scene.dx_m=3.3333e-5", f"scene.radius_m={1e-3 if th < 45 else 5e-4}"]
        _, cfg = load_case(case, over + a.set)
        ck = None if a.checkpoint_dir is None else a.checkpoint_dir / f"theta_{th:03.0f}.pt"
        r = settle(case, over + a.set, checkpoint=ck)
        ang = r["angles"]
        cap = (cfg["surface"]["tension_N_m"] / cfg["fluid"]["viscosity_Pa_s"])
        print(f"| {th:.0f}° | {start:.0f}° | {cfg['scene']['radius_m'] * 1e3:.2f} mm, {cfg['scene']['dx_m'] * 1e3:.4f} mm | "
              f"{sum(ang) / len(ang):.1f}° | {min(ang):.1f}–{max(ang):.1f}° | {max(r['speeds']) / cap:.1e} | "
              f"{r['particles']} | {r['wall_s']:.0f} s |", flush=True)


if __name__ == "__main__":
    main()
