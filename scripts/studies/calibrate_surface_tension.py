"""Stalagmometric calibration (thesis §5.1, SPEC 3b): a drop hangs from the end of a vertical
wire (`cases/pendant_drop`), gravity is ramped up slowly, and part of the drop falls off.
Tate's law with the Harkins-Brown factor says the falling mass m at the load g obeys
m g = 2 pi r sigma f(r / V^(1/3)) (r the wire's radius, V = m / rho); the ratio
q = m g / (2 pi r sigma f) measured at the pinch-off says how the model's surface-tension
coefficient alpha compares with the sigma it stands for (q = 1: consistent).

    python scripts/studies/calibrate_surface_tension.py --tate              # q at alpha = sigma, wires of 1 and 1.5 mm
    python scripts/studies/calibrate_surface_tension.py --material steel --dx 1.25e-4 1e-4 8.75e-5   # alpha(sigma, dx)

The calibration finds, per dx, the alpha at which the drop detaches at Tate's load (q = 1):
a bisection on alpha over a bracket [alpha with q < 1, alpha with q > 1], whose next trial is
the quasi-static scaling step alpha / q when that lies inside the bracket (the detaching load
is proportional to alpha when the loading is slow: every force that holds the drop is), else
the bracket's geometric middle; it stops at |q - 1| < --tolerance.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from torchsph.core.analytic import tate_mass  # noqa: E402
from torchsph.post.caps import PENDANT_LIQUIDS as MATERIALS, detach  # noqa: E402

CASE = ROOT / "cases" / "pendant_drop"


def trial(mat: dict, dx: float, d_wire: float, alpha: float, law: str = "harkins-brown") -> dict:
    """One ramped pendant drop: the measured fall, Tate-Harkins-Brown's mass at its load, q."""
    over = mat["over"] + [f"scene.dx_m={dx}", f"scene.wire_diameter_m={d_wire}",
                          f"surface.tension_N_m={alpha}"]
    r = detach(CASE, over)
    if not r["detached"]:
        raise SystemExit(f"alpha = {alpha:g}: the drop still hangs at the ramp's end (g = {r['g']:.1f}); "
                         "raise fluid.gravity_m_s2")
    try:
        m_t, f = tate_mass(d_wire / 2, mat["sigma"], r["g"], mat["rho"])
    except ValueError:  # a drop this heavy at this load lies beyond Harkins and Brown's table
        m_t = f = float("nan")
    r.update(m_tate=m_t, f=f, psi=d_wire / 2 / (r["m_fallen"] / mat["rho"]) ** (1 / 3), alpha=alpha, dx=dx, d=d_wire,
             q_hb=r["m_fallen"] / m_t,  # Tate with Harkins-Brown: the falling mass
             q_tate=r["m_drop"] * r["g"] / (math.pi * d_wire * mat["sigma"]))  # the thesis's (4.1): the drop's mass
    r["q"] = r["q_tate" if law == "tate" else "q_hb"]  # what the calibration matches
    return r


def row(r: dict, sigma: float) -> str:
    return (f"| {r['d'] * 1e3:.2f} | {r['dx'] * 1e3:.3f} | {r['particles']} | {r['alpha'] / sigma:.3f} | "
            f"{r['m_drop'] * 1e6:.3f} | {r['t'] * 1e3:.1f} | {r['g']:.1f} | {r['m_fallen'] * 1e6:.3f} | "
            f"{r['psi']:.3f} | {r['f']:.3f} | {r['m_tate'] * 1e6:.3f} | {100 * (r['q_hb'] - 1):+.1f} % | "
            f"{r['q_tate']:.3f} | {r['steps']} | {r['wall_s']:.0f} |")


HEADER = ("| wire d (mm) | dx (mm) | particles | alpha / sigma | drop (mg) | pinch-off (ms) | g then (m/s²) | "
          "fallen m (mg) | r / V^(1/3) | f (H-B) | Tate-H-B m (mg) | m / Tate-H-B - 1 | drop g / (π d σ) | steps | wall s |\n"
          "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")


def calibrate(mat: dict, dx: float, d_wire: float, tol: float, iterations: int, law: str) -> tuple[float, float, float]:
    """(the last alpha tried, its q, the next alpha the search would try): the next equals the
    last when |q - 1| < tol."""
    sigma = mat["sigma"]
    lo = hi = None  # alphas with q < 1 and q > 1
    alpha, q = sigma, float("nan")
    for i in range(iterations):
        r = trial(mat, dx, d_wire, alpha, law)
        print(row(r, sigma), flush=True)
        q = r["q"]
        if math.isnan(q):
            return alpha, q, float("nan")
        if abs(q - 1) < tol:
            return alpha, q, alpha
        if q < 1:
            lo = alpha
        else:
            hi = alpha
        step = alpha / q
        nxt = step if (lo is None or step > lo) and (hi is None or step < hi) else math.sqrt(lo * hi)
        if i == iterations - 1:
            return alpha, q, nxt
        alpha = nxt
    return alpha, q, alpha


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--material", choices=sorted(MATERIALS), default="water-like")
    ap.add_argument("--dx", type=float, nargs="*", default=[1.0e-4])
    ap.add_argument("--wire", type=float, nargs="*", default=None, help="wire diameters, m (default: 1 mm; "
                    "steel: 1.2 mm, Table 2; water-like with --tate: 1 and 1.5 mm)")
    ap.add_argument("--tate", action="store_true", help="only measure q at alpha = sigma (no calibration)")
    ap.add_argument("--law", choices=("harkins-brown", "tate"), default="harkins-brown",
                    help="calibrate against Tate's law with the Harkins-Brown factor (the falling mass), or "
                         "the thesis's plain Tate law (4.1), m g = pi d sigma with the drop's whole mass")
    ap.add_argument("--tolerance", type=float, default=0.03)
    ap.add_argument("--iterations", type=int, default=5)
    ap.add_argument("--set", action="append", default=[], help="extra case override, SECTION.KEY=VALUE")
    args = ap.parse_args()
    mat = MATERIALS[args.material]
    mat = {**mat, "over": mat["over"] + args.set}
    wires = args.wire or ([1.2e-3] if args.material == "steel" else [1.0e-3, 1.5e-3] if args.tate else [1.0e-3])
    print(f"{args.material}: sigma = {mat['sigma']} N/m, rho = {mat['rho']} kg/m^3; gravity ramped "
          f"(cases/pendant_drop; overrides {' '.join(mat['over']) or 'none'})")
    print(HEADER)
    results = []
    for d in wires:
        for dx in args.dx:
            if args.tate:
                print(row(trial(mat, dx, d, mat["sigma"]), mat["sigma"]), flush=True)
            else:
                results.append((d, dx, *calibrate(mat, dx, d, args.tolerance, args.iterations, args.law)))
    if results:
        print(f"\n| wire d (mm) | dx (mm) | last alpha / sigma tried | q there ({args.law}) | "
              "calibrated alpha / sigma (next trial) |\n|---|---|---|---|---|")
        for d, dx, a, q, nxt in results:
            print(f"| {d * 1e3:.2f} | {dx * 1e3:.3f} | {a / mat['sigma']:.3f} | {q:.3f} | {nxt / mat['sigma']:.3f} |")


if __name__ == "__main__":
    main()
