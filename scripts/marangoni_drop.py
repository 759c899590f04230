"""Thesis §5.2: thermocapillary circulation in a heated free drop. Prints the history of
the centre velocity (Shepard average within 2 dx of the centre of mass) and, at the end,
the profile of u_z along x through the centre.

    python scripts/marangoni_drop.py cases/marangoni_drop_steel
    python scripts/marangoni_drop.py cases/marangoni_drop_titanium --set scene.dx_m=0.1e-3
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

from torchsph.config import load_case  # noqa: E402
from torchsph.runner import make_simulation, run_steps  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case")
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--t-end", type=float, default=None)
    ap.add_argument("--samples", type=int, default=15)
    args = ap.parse_args()
    _, cfg = load_case(args.case, args.set)
    scene, sim = make_simulation(cfg)
    t_end = args.t_end or cfg["run"]["t_end_s"]
    dx = scene.dx
    t0 = time.perf_counter()
    print("| t (s) | centre u_z (mm/s) | max |u| (mm/s) | T max (K) | drop's mean u_z (mm/s) |")
    print("|---|---|---|---|---|")
    for k in range(1, args.samples + 1):
        run_steps(sim, t_end=t_end * k / args.samples)
        s = sim.state
        c = s.x.mean(0)
        near = (s.x - c).norm(dim=-1) < 2 * dx
        uc = s.v[near].mean(0)
        u_com = (s.m.unsqueeze(-1) * s.v).sum(0) / s.m.sum()
        print(f"| {sim.t:.4f} | {float(uc[2]) * 1e3:.3f} | {float(s.v.norm(dim=-1).max()) * 1e3:.3f} | "
              f"{float(s.T.max()):.0f} | {float(u_com[2]) * 1e3:.3g} |", flush=True)
    s = sim.state
    c = s.x.mean(0)
    line = ((s.x[:, 1] - c[1]).abs() < dx) & ((s.x[:, 2] - c[2]).abs() < dx)
    xb = torch.round((s.x[line, 0] - c[0]) / dx)
    print("\nprofile at t = %.4f s through the centre (|y|, |z| < dx, binned by dx): x (mm), u_z (mm/s)" % sim.t)
    for b in torch.unique(xb).tolist():
        sel = xb == b
        print(f"{b * dx * 1e3:8.3f} {float(s.v[line][sel, 2].mean()) * 1e3:9.3f}")
    print(f"\n{sim.step} steps, {s.n} particles, {time.perf_counter() - t0:.0f} s wall")


if __name__ == "__main__":
    main()
