"""Thesis §5.2: thermocapillary circulation in a heated free drop. Prints the history of
the centre velocity (mean of the particles within 2 dx of the centre of mass), and the
profile of u_z along x through the centre at the end and averaged over the last third of
the run (the flow at these Reynolds numbers, ~10^3, is unsteady: the averages are the
numbers to compare between resolutions).

    python scripts/studies/marangoni_drop.py cases/marangoni_drop_steel
    python scripts/studies/marangoni_drop.py cases/marangoni_drop_titanium --set scene.dx_m=0.25e-3
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

from torchsph.io.config import load_case  # noqa: E402
from torchsph.run.build import make_simulation  # noqa: E402
from torchsph.step.loop import run_steps  # noqa: E402


def profile(s, dx, c, edges):
    """u_z of the particles within dx of the x axis through c, binned by x - c[0]."""
    line = ((s.x[:, 1] - c[1]).abs() < dx) & ((s.x[:, 2] - c[2]).abs() < dx)
    k = torch.bucketize(s.x[line, 0] - c[0], edges) - 1
    ok = (k >= 0) & (k < edges.numel() - 1)
    nb = edges.numel() - 1
    su = torch.zeros(nb, dtype=s.x.dtype).index_add_(0, k[ok], s.v[line][ok, 2])
    n = torch.zeros(nb, dtype=s.x.dtype).index_add_(0, k[ok], torch.ones_like(s.v[line][ok, 2]))
    return su, n


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case")
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--t-end", type=float, default=None)
    ap.add_argument("--samples", type=int, default=30)
    args = ap.parse_args()
    _, cfg = load_case(args.case, args.set)
    scene, sim = make_simulation(cfg)
    t_end = args.t_end or cfg["run"]["t_end_s"]
    dx = scene.dx
    R = 0.5 * cfg["scene"]["size_m"]
    edges = torch.arange(-R, R + 1e-12, 0.25e-3, dtype=sim.state.dtype)  # 0.25 mm bins at any dx
    acc_u, acc_n, centre = torch.zeros(edges.numel() - 1, dtype=edges.dtype), torch.zeros(edges.numel() - 1, dtype=edges.dtype), []
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
        if 3 * k >= 2 * args.samples:  # the last third: averages
            su, n = profile(s, dx, c, edges)
            acc_u, acc_n = acc_u + su, acc_n + n
            centre.append(float(uc[2]))
    s = sim.state
    su, n = profile(s, dx, s.x.mean(0), edges)
    mid = 0.5 * (edges[1:] + edges[:-1])
    print(f"\ncentre u_z averaged over the last third ({len(centre)} samples): "
          f"{sum(centre) / len(centre) * 1e3:.1f} mm/s (min {min(centre) * 1e3:.1f}, max {max(centre) * 1e3:.1f})")
    print(f"\nprofile of u_z along x through the centre (|y|, |z| < dx, 0.25 mm bins): x (mm), "
          f"at t = {sim.t:.4f} s, and averaged over the last third (mm/s)")
    for j in range(mid.numel()):
        now = float(su[j] / n[j]) * 1e3 if n[j] > 0 else float("nan")
        avg = float(acc_u[j] / acc_n[j]) * 1e3 if acc_n[j] > 0 else float("nan")
        print(f"{float(mid[j]) * 1e3:8.3f} {now:9.1f} {avg:9.1f}")
    print(f"\n{sim.step} steps, {s.n} particles, {time.perf_counter() - t0:.0f} s wall")


if __name__ == "__main__":
    main()
