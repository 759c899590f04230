"""Regenerate the README's verification table for the solver core.

    python scripts/verify.py

Each row: the study, the measured error, the tolerance the tests assert, and the wall
time. The same checks (with the same tolerances) run in ``tests/``.
"""
from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchsph.config import load_case  # noqa: E402
from torchsph.kernels import KERNELS, make_kernel  # noqa: E402
from torchsph.runner import make_simulation, run_steps  # noqa: E402
from torchsph.scenes import poiseuille_exact, taylor_green_exact  # noqa: E402


def case(name, *ov):
    _, cfg = load_case(ROOT / "cases" / name, list(ov))
    return make_simulation(cfg)


def kernels():
    worst = 0.0
    for name in KERNELS:
        for dim in (2, 3):
            k = make_kernel(name, dim)
            r = torch.linspace(0, k.radius(1.0), 200001, dtype=torch.float64)
            shell = 2 * math.pi * r if dim == 2 else 4 * math.pi * r * r
            worst = max(worst, abs(float(torch.trapezoid(k.w(r, 1.0) * shell, r)) - 1))
    return f"max abs(int W dV - 1) = {worst:.1e}", "< 1e-3"


def taylor_green():
    scene, sim = case("taylor_green_2d", "scene.nx=50")
    run_steps(sim, t_end=0.2)
    i = scene.info
    exact = i["U"] * math.exp(-8 * math.pi**2 * i["nu"] * 0.2)
    sp = sim.state.v.norm(dim=-1)
    ue = taylor_green_exact(sim.state.x, 0.2, i["L"], i["U"], i["nu"]).norm(dim=-1)
    return (f"max speed error {abs(float(sp.max()) / exact - 1) * 100:.2f} %, "
            f"L1 {float((sp - ue).abs().mean() / ue.mean()) * 100:.2f} %"), "< 2 %"


def poiseuille():
    scene, sim = case("poiseuille_2d")
    run_steps(sim, t_end=0.8)
    i, s, f = scene.info, sim.state, sim.fluid_mask
    ue = poiseuille_exact(s.x[f, 1], math.inf, i["H"], i["F"], i["nu"])
    return f"max abs(u - u_exact) / u_max = {float((s.v[f, 0] - ue).abs().max()) / i['u_max'] * 100:.2f} %", "< 2 %"


def tank():
    scene, sim = case("hydrostatic_tank_3d")
    run_steps(sim, t_end=0.25)
    i, s, f = scene.info, sim.state, sim.fluid_mask
    pe = i["rho0"] * i["g"] * (i["depth"] - i["z0"][s.id[f]])
    scale = i["rho0"] * i["g"] * i["depth"]
    return f"max abs(p - rho g depth) / (rho g D) = {float((s.p[f] - pe).abs().max()) / scale * 100:.2f} %", "< 2 %"


def conduction():
    from torchsph.scenes import conduction_1d_exact
    from torchsph.state import Phase

    errs = []
    nxs = [25, 50, 100, 200]
    for nx in nxs:
        scene, sim = case("conduction_1d", f"scene.nx={nx}")
        run_steps(sim, t_end=0.3)
        s, i = sim.state, scene.info
        m = s.phase == Phase.SOLID
        Te = conduction_1d_exact(s.x[m, 0], sim.t, i["alpha"], i["T_face"], i["T0"])
        errs.append(float(torch.sqrt(((s.T[m] - Te) ** 2).mean()) / (i["T_face"] - i["T0"])))
    orders = [math.log(errs[k] / errs[k + 1]) / math.log(2) for k in range(len(errs) - 1)]
    return ("L2 / dT at nx = 25, 50, 100, 200: " + ", ".join(f"{e:.2e}" for e in errs)
            + "; orders " + ", ".join(f"{o:.2f}" for o in orders)), "L2 < 0.5 %, order >= 1.5 (25-50-100)"


def bump():
    from torchsph.scenes import gaussian_bump_exact

    scene, sim = case("gaussian_bump_3d")
    run_steps(sim, t_end=0.004)
    i = scene.info
    Te = gaussian_bump_exact(sim.state.x, sim.t, i["alpha"], i["center"], i["sigma"], i["A"], i["Tb"],
                             scene.domain)
    err = float((sim.state.T - Te).abs().max()) / i["A"]
    peak = float(sim.state.T.max() - i["Tb"]) / float(Te.max() - i["Tb"]) - 1
    return f"max error {err * 100:.2f} % of A; peak {peak * 100:+.1f} % of the exact peak", "< 1 % of A"


def stefan():
    from torchsph.state import Phase
    from torchsph.thermal import melt_front, neumann_lambda

    scene, sim = case("stefan_1d")
    run_steps(sim, t_end=0.5)
    _, cfg = load_case(ROOT / "cases" / "stefan_1d")
    th, i, s = cfg["thermal"], scene.info, sim.state
    T_m = 0.5 * (th["solidus_K"] + th["liquidus_K"])
    lam = neumann_lambda(th["specific_heat_J_kgK"] * (i["T_face"] - T_m) / th["latent_heat_J_kg"])
    m = s.phase == Phase.SOLID
    err = melt_front(s.x[m, 0], s.T[m], T_m) / (2 * lam * math.sqrt(i["alpha"] * sim.t)) - 1
    return f"front position error {err * 100:+.2f} % at t = 0.5 s", "< 3 %"


ROWS = [
    ("Kernel normalisation (cubic spline, Wendland C2; 2-D, 3-D)", kernels),
    ("Taylor-Green vortex, 50^2, t = 0.2, float64", taylor_green),
    ("Poiseuille channel, 20 across, steady (t = 0.8 s)", poiseuille),
    ("Hydrostatic tank 3-D, 10^3 fluid, t = 0.25 s", tank),
    ("Transient conduction vs erfc (2-D prism, t = 0.3 s)", conduction),
    ("3-D Gaussian bump diffusion, 24^3, t = 4 ms", bump),
    ("One-phase Stefan melting vs Neumann (St = 0.83)", stefan),
]


def main():
    print("| study | measured | test asserts | wall s |")
    print("|---|---|---|---|")
    for title, fn in ROWS:
        t = time.perf_counter()
        got, tol = fn()
        print(f"| {title} | {got} | {tol} | {time.perf_counter() - t:.1f} |", flush=True)


if __name__ == "__main__":
    main()
