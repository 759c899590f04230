"""Stalagmometric calibration (thesis §5.1): a drop of known mass m hangs from the end of a
vertical wire of diameter d; by Tate's law it detaches when m g = pi d sigma. With gravity
set to g = sigma pi d / m, bisection on the model's alpha finds the alpha at which the drop
just detaches: alpha / sigma says whether the CSF model needs calibrating (1 = consistent).

    python scripts/studies/calibrate_surface_tension.py                 # dx = 0.125 mm
    python scripts/studies/calibrate_surface_tension.py --dx 0.1e-3 0.15e-3 --iterations 5

The wire is a cylinder of wall particles (no-slip, Adami pressure: the melt wets its end);
the drop is a ball of radius R touching the wire's end face. "Detached" = the drop's centre
of mass has fallen more than 1.5 R within t_end. Note that Tate's law ignores the part of
the drop that stays on the wire (the Harkins-Brown factor, ~0.6 for real liquids), so the
procedure calibrates alpha against that simplified law, as the thesis did.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from torchsph.config import load_case  # noqa: E402
from torchsph.runner import make_simulation, run_steps  # noqa: E402
from torchsph.scenes import build_scene, lattice  # noqa: E402
from torchsph.simulation import SimulationError  # noqa: E402
from torchsph.state import ParticleState, Phase  # noqa: E402

SIGMA, RHO, R_DROP, D_WIRE = 0.05, 1000.0, 1.0e-3, 1.0e-3


def detaches(alpha: float, dx: float, t_end: float, compile: bool, angle: float | None = None) -> tuple[bool, float]:
    mass = RHO * 4.0 / 3.0 * math.pi * R_DROP**3
    g = SIGMA * math.pi * D_WIRE / mass
    over = [f"scene.dx_m={dx}", f"scene.size_m={2 * R_DROP}", f"surface.tension_N_m={alpha}",
            f"fluid.gravity_m_s2=[0.0, 0.0, {-g}]", "numerics.damping_time_s=0.0",
            f"run.t_end_s={t_end}", f"numerics.compile={'true' if compile else 'false'}"]
    if angle is not None:  # the wetting model between the melt and the wire (SPEC 3b)
        over.append(f"surface.contact_angle_deg={angle}")
    _, cfg = load_case(ROOT / "cases" / "static_drop_3d", over)
    scene = build_scene(cfg)
    drop = scene.state
    # the wire: a vertical cylinder of wall particles whose end face touches the drop's top
    layers = 8
    n = math.ceil(D_WIRE / dx) + 2
    top = float(drop.x[:, 2].max()) + dx
    w = lattice((n, n, layers), dx, origin=(-n * dx / 2, -n * dx / 2, top - 0.5 * dx), dtype=drop.dtype)
    w = w[(w[:, 0] ** 2 + w[:, 1] ** 2) < (D_WIRE / 2) ** 2]
    wire = ParticleState.create(w, torch.zeros_like(w), RHO, RHO * dx**3, Phase.WALL,
                                T=cfg["fluid"]["temperature_K"], id=torch.arange(w.shape[0]) + drop.n,
                                dtype=drop.dtype)
    scene.state = ParticleState.cat([drop, wire])
    _, sim = make_simulation(cfg, scene=scene)
    fluid = sim.state.phase == Phase.FLUID
    z0 = float(sim.state.x[fluid, 2].mean())
    try:
        run_steps(sim, t_end=t_end)
    except SimulationError:
        return True, float("nan")
    fall = z0 - float(sim.state.x[fluid, 2].mean())
    return fall > 1.5 * R_DROP, fall


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dx", type=float, nargs="*", default=[0.125e-3])
    ap.add_argument("--iterations", type=int, default=5)
    ap.add_argument("--t-end", type=float, default=0.03)
    ap.add_argument("--compile", action="store_true")
    ap.add_argument("--contact-angle", type=float, default=None,
                    help="theta_eq between drop and wire (deg; default: no wetting model)")
    ap.add_argument("--alpha", type=float, nargs="*", default=None,
                    help="only try these alpha / sigma (no bisection)")
    args = ap.parse_args()
    print(f"sigma = {SIGMA} N/m, drop R = {R_DROP * 1e3} mm, wire d = {D_WIRE * 1e3} mm, "
          f"g = sigma pi d / m = {SIGMA * math.pi * D_WIRE / (RHO * 4 / 3 * math.pi * R_DROP**3):.2f} m/s^2")
    print("| dx (mm) | alpha tried / sigma | detached | fall (mm) | wall s |")
    print("|---|---|---|---|---|")
    results = []
    for dx in args.dx:
        if args.alpha:
            for a in args.alpha:
                t0 = time.perf_counter()
                det, fall = detaches(a * SIGMA, dx, args.t_end, args.compile, args.contact_angle)
                print(f"| {dx * 1e3:.3f} | {a:.3f} | {det} | {fall * 1e3:.2f} | {time.perf_counter() - t0:.0f} |", flush=True)
            continue
        lo, hi = 0.25, 4.0  # alpha / sigma: detaches at lo, holds at hi (checked below)
        for a in (lo, hi):
            t0 = time.perf_counter()
            det, fall = detaches(a * SIGMA, dx, args.t_end, args.compile, args.contact_angle)
            print(f"| {dx * 1e3:.3f} | {a:.3f} | {det} | {fall * 1e3:.2f} | {time.perf_counter() - t0:.0f} |", flush=True)
        for _ in range(args.iterations):
            mid = math.sqrt(lo * hi)
            t0 = time.perf_counter()
            det, fall = detaches(mid * SIGMA, dx, args.t_end, args.compile, args.contact_angle)
            print(f"| {dx * 1e3:.3f} | {mid:.3f} | {det} | {fall * 1e3:.2f} | {time.perf_counter() - t0:.0f} |", flush=True)
            lo, hi = (mid, hi) if det else (lo, mid)
        results.append((dx, math.sqrt(lo * hi), hi / lo))
    print("\n| dx (mm) | calibrated alpha / sigma | bracket ratio |")
    print("|---|---|---|")
    for dx, a, br in results:
        print(f"| {dx * 1e3:.3f} | {a:.3f} | {br:.3f} |")


if __name__ == "__main__":
    main()
