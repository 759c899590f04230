"""Regenerate the README's verification table for the solver core.

    python scripts/tools/verify.py

Each row: the study, the measured error, the tolerance the tests assert, and the wall
time. The same checks (with the same tolerances) run in ``tests/``.
"""
from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from torchsph.io.config import load_case  # noqa: E402
from torchsph.core.kernels import KERNELS, make_kernel  # noqa: E402
from torchsph.run.build import make_simulation  # noqa: E402
from torchsph.step.loop import run_steps  # noqa: E402
from torchsph.core.analytic import poiseuille_exact, taylor_green_exact  # noqa: E402


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
    from torchsph.core.analytic import conduction_1d_exact
    from torchsph.core.state import Phase

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
    from torchsph.core.analytic import gaussian_bump_exact

    scene, sim = case("gaussian_bump_3d")
    run_steps(sim, t_end=0.004)
    i = scene.info
    Te = gaussian_bump_exact(sim.state.x, sim.t, i["alpha"], i["center"], i["sigma"], i["A"], i["Tb"],
                             scene.domain)
    err = float((sim.state.T - Te).abs().max()) / i["A"]
    peak = float(sim.state.T.max() - i["Tb"]) / float(Te.max() - i["Tb"]) - 1
    return f"max error {err * 100:.2f} % of A; peak {peak * 100:+.1f} % of the exact peak", "< 1 % of A"


def stefan():
    from torchsph.core.state import Phase
    from torchsph.core.analytic import melt_front, neumann_lambda

    scene, sim = case("stefan_1d")
    run_steps(sim, t_end=0.5)
    _, cfg = load_case(ROOT / "cases" / "stefan_1d")
    th, i, s = cfg["thermal"], scene.info, sim.state
    T_m = 0.5 * (th["solidus_K"] + th["liquidus_K"])
    lam = neumann_lambda(th["specific_heat_J_kgK"] * (i["T_face"] - T_m) / th["latent_heat_J_kg"])
    m = s.phase == Phase.SOLID
    err = melt_front(s.x[m, 0], s.T[m], T_m) / (2 * lam * math.sqrt(i["alpha"] * sim.t)) - 1
    return f"front position error {err * 100:+.2f} % at t = 0.5 s", "< 3 %"


def beams():
    from torchsph.physics.beam import Beam, beam_power, gaussian_fraction_in_strip
    from torchsph.scenes.builders import lattice

    def plate(n, dx, tilt):
        x = lattice((n, 80, 5), dx, origin=(-n * dx / 2, -80 * dx / 2, -5 * dx), dtype=torch.float64)
        c, s = math.cos(math.radians(tilt)), math.sin(math.radians(tilt))
        return x @ torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=torch.float64).T

    b = Beam(300.0, 0.85, 0.75e-3, (math.sqrt(0.5), 0.0, -math.sqrt(0.5)), (0.0, 0.0, 0.0))
    one = lambda x: torch.ones(x.shape[0], dtype=torch.bool)  # noqa: E731
    flat = float(beam_power(plate(110, 1e-4, 0.0), one(plate(110, 1e-4, 0.0)), b, 0, 1e-4).sum()) / 255 - 1
    xt = plate(110, 1e-4, 20.0)
    tilt = float(beam_power(xt, one(xt), b, 0, 1e-4).sum()) / 255 - 1
    dx, d = 0.05e-3, 1.2e-3
    n = round(d / dx)
    xc = lattice((n, n, 140), dx, origin=(-d / 2, -d / 2, -3.5e-3), dtype=torch.float64)
    xc = xc[(xc[:, 0] ** 2 + xc[:, 1] ** 2) < (d / 2) ** 2]
    cyl = float(beam_power(xc, one(xc), b, 0, dx).sum()) / (255 * gaussian_fraction_in_strip(d, 0.75e-3)) - 1
    # a block on a plate whose lattice is offset from it by half a spacing (a wire over a substrate)
    m, dx = 12, 1e-4
    xb = torch.cat([lattice((m, m, m), dx, origin=(-(m - 1) * dx / 2, -(m - 1) * dx / 2, 0.5 * dx), dtype=torch.float64),
                    plate(110, dx, 0.0)])
    blk = float(beam_power(xb, one(xb), b, 0, dx).sum()) / 255 - 1
    return (f"flat {flat * 100:+.1e} %, plate tilted 20 deg {tilt * 100:+.1e} %, 1.2 mm wire "
            f"{cyl * 100:+.3f} % (vs eta0 Q0 erf(d / sqrt(2) r)), a block on a half-offset lattice {blk * 100:+.1e} %"), \
        "1 % flat, 2 % tilted / wire, 1e-4 % block"


def radiation():
    from torchsph.physics.losses import SIGMA_SB
    scene, sim = case("radiating_slab", "scene.dx_m=0.2e-3", "run.t_end_s=0.5")
    s = sim.state
    M, A = float(s.m.sum()), 2 * 1.2e-3 * 1.2e-3
    run_steps(sim, t_end=0.5)
    T, n = 1500.0, 20000
    f = lambda T: -SIGMA_SB * 0.4 * A * (T**4 - 300.0**4) / (M * 450.0)  # noqa: E731
    for _ in range(n):
        k1 = f(T); k2 = f(T + 0.5 / n / 2 * k1); k3 = f(T + 0.5 / n / 2 * k2); k4 = f(T + 0.5 / n * k3)  # noqa: E702
        T += 0.5 / n / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    T_sph = float((s.T * s.m).sum() / s.m.sum())
    return f"temperature drop {((1500 - T_sph) / (1500 - T) - 1) * 100:+.2f} % vs the ODE at t = 0.5 s", "< 1 %"


def balance():
    _, sim = case("beam_plate", "run.t_end_s=0.02", "thermal.emissivity=0.4", "thermal.evaporation=true")
    run_steps(sim, t_end=0.02)
    e = sim.energy_balance()
    return (f"beam {e['beam_J']:.4f} J, radiated {e['radiation_J']:.2e} J, evaporated "
            f"{e['evaporation_J']:.2e} J, stored {e['stored_J']:.4f} J; residual {e['residual_rel']:.1e} of the flows"
            ), "< 1 % of absorbed"


def heating():
    from torchsph.core.analytic import box_source_rise

    errs = []
    for dx in ("0.2e-3", "0.1e-3"):
        _, sim = case("preheated_block", f"scene.dx_m={dx}")
        run_steps(sim, t_end=0.01)
        s = sim.state
        probes = torch.tensor([[0.0, 0.0, -1.6e-3], [0.55e-3, 0.0, -1.6e-3], [1.1e-3, 0.0, -1.6e-3]], dtype=torch.float64)
        idx = torch.cdist(probes, s.x).argmin(1)
        ex = box_source_rise(s.x[idx], sim.t, [-0.6e-3, -0.6e-3, -2.2e-3], [0.6e-3, 0.6e-3, -1.0e-3], 42.0 / (7890 * 450.0),
                             7890 * 450.0, 1e10, [(-2e-3, 2e-3), (-2e-3, 2e-3), (-3e-3, 0.0)])
        errs.append(float((s.T[idx] - 300.0 - ex).abs().max()) / float(ex[0]))
    e = sim.energy_balance()
    return (f"max T error at 3 probes {errs[0] * 100:.1f} % (dx 0.2 mm), {errs[1] * 100:.2f} % (0.1 mm) of the rise; "
            f"energy residual {e['residual_rel']:.1e}"), "< 1.5 % at 0.1 mm, x2.5 smaller"


def bump_window():
    """The conduction window (numerics.conduction_window = 0.25) on the bump with dt held at a 40th of
    the thermal limit (as the melt's acoustic step holds the deposition's solid), against the exact
    solution and against every-step conduction (tests/test_thermal.py)."""
    from torchsph.core.analytic import gaussian_bump_exact

    out = {}
    for w in (0.0, 0.25):
        scene, sim = case("gaussian_bump_3d", "numerics.dt_s=2.5e-6", "run.t_end_s=0.002", f"numerics.conduction_window={w}")
        H0 = float((sim.state.m * sim.thermal.to_enthalpy(sim.state.T)).sum())
        run_steps(sim, t_end=0.002)
        i = scene.info
        Te = gaussian_bump_exact(sim.state.x, sim.t, i["alpha"], i["center"], i["sigma"], i["A"], i["Tb"], scene.domain)
        H1 = float((sim.state.m * sim.thermal.to_enthalpy(sim.state.T)).sum())
        out[w] = (sim.state.T.clone(), float((sim.state.T - Te).abs().max()) / i["A"], abs(H1 - H0) / H0)
    d = float((out[0.25][0] - out[0.0][0]).abs().max()) / 1000.0
    return (f"max error {out[0.25][1] * 100:.2f} % of A (every step {out[0.0][1] * 100:.2f} %), {d * 100:.3f} % of A "
            f"from every step; energy {out[0.25][2]:.1e}", "< 1 % of A; < 0.2 % of A from every step; energy < 1e-13")


def anisotropic():
    from torchsph.core.analytic import conduction_1d_exact
    from torchsph.core.state import Phase

    errs = []
    for nx in (25, 50, 100):
        scene, sim = case("anisotropic_conduction_1d", f"scene.nx={nx}")
        run_steps(sim, t_end=0.15)
        s, i = sim.state, scene.info
        m = s.phase == Phase.SOLID
        alpha_x = (42.0 + 42.0) / (7890.0 * 450.0)  # (the case's k + k_x) / (rho c_p)
        Te = conduction_1d_exact(s.x[m, 0], sim.t, alpha_x, i["T_face"], i["T0"])
        errs.append(float(torch.sqrt(((s.T[m] - Te) ** 2).mean()) / (i["T_face"] - i["T0"])))
    orders = [math.log(errs[k] / errs[k + 1]) / math.log(2) for k in range(len(errs) - 1)]
    return ("L2 / dT at nx = 25, 50, 100: " + ", ".join(f"{e:.2e}" for e in errs)
            + "; orders " + ", ".join(f"{o:.2f}" for o in orders)), "L2 < 0.5 %, order >= 0.9 (50-100)"


ROWS = [
    ("Kernel normalisation (cubic spline, Wendland C2; 2-D, 3-D)", kernels),
    ("Taylor-Green vortex, 50^2, t = 0.2, float64", taylor_green),
    ("Poiseuille channel, 20 across, steady (t = 0.8 s)", poiseuille),
    ("Hydrostatic tank 3-D, 10^3 fluid, t = 0.25 s", tank),
    ("Transient conduction vs erfc (2-D prism, t = 0.3 s)", conduction),
    ("3-D Gaussian bump diffusion, 24^3, t = 4 ms", bump),
    ("The same bump, conduction window 0.25, dt = thermal limit / 40, t = 2 ms", bump_window),
    ("One-phase Stefan melting vs Neumann (St = 0.83)", stefan),
    ("Absorbed beam power, 300 W, eta0 = 0.85, beam at 45 deg", beams),
    ("Radiative cooling of an isothermal slab vs the ODE", radiation),
    ("Energy balance: beam + radiation + evaporation, 20 ms", balance),
    ("Volumetric heat source in a box inside a cold block vs the exact solution, 10 ms", heating),
    ("Two-stage conduction (grad_T field, then its flux divergence) k + k_x = 84 along a bar vs erfc, t = 0.15 s",
     anisotropic),
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
