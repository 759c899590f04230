"""Free-surface forces (SPEC 2.4-2.6, 3.9-3.12): CSF surface tension, Marangoni, recoil,
checked against the Laplace jump, the relaxation of a square drop, Rayleigh's oscillation
period, the Birikh thermocapillary return flow and the integrated recoil pressure."""
import math

import pytest
import torch
from conftest import CASES, assert_blow_up_diagnosed

from torchsph.core.kernels import make_kernel
from torchsph.core.neighbors import Domain, NeighbourTable
from torchsph.core.state import ParticleState, Phase
from torchsph.io.config import CaseError, load_case
from torchsph.physics.losses import SurfaceLosses
from torchsph.physics.surface import SurfaceForces, SurfaceParams
from torchsph.run.build import make_simulation
from torchsph.scenes.builders import lattice
from torchsph.step.loop import run_steps
from torchsph.step.simulation import SimulationError

torch.set_num_threads(1)  # these scenes are small: threads only add overhead


def drop_pressure_jump(case, over, t_end, t_avg):
    """Mean pressure inside r < R/2, averaged over the steps with t > t_avg, over the
    Laplace jump (d - 1) sigma / R; and the largest spurious speed over sigma / eta."""
    _, cfg = load_case(CASES / case, over)
    scene, sim = make_simulation(cfg)
    R, d = scene.info["R"], cfg["scene"]["dim"]
    sigma, eta = cfg["surface"]["tension_N_m"], cfg["fluid"]["viscosity_Pa_s"]
    acc = []

    def cb(sim, info):
        if sim.t > t_avg:
            r = sim.state.x.norm(dim=-1)
            acc.append(float(sim.state.p[r < 0.5 * R].mean()))

    run_steps(sim, t_end=t_end, callback=cb)
    jump = sum(acc) / len(acc) / ((d - 1) * sigma / R)
    spurious = float(sim.state.v.norm(dim=-1).max()) / (sigma / eta)
    return jump, spurious


def test_static_drop_2d_laplace_jump():
    """2-D drop, R = 15 dx, no gravity: p_in = sigma / R within 5 %."""
    jump, spurious = drop_pressure_jump("static_drop_2d", ["scene.dx_m=6.6667e-5", "run.t_end_s=0.012",
                                                           "numerics.damping_time_s=0.006"], 0.012, 0.006)
    print(f"2-D: p_in / (sigma / R) = {jump:.4f}, max |u| / (sigma / eta) = {spurious:.2e}")
    assert abs(jump - 1.0) < 0.05
    assert spurious < 1e-2


@pytest.mark.slow
def test_static_drop_3d_laplace_jump():
    """3-D drop, R = 8 dx: p_in = 2 sigma / R within 5 % (slow: ~3 min)."""
    jump, spurious = drop_pressure_jump("static_drop_3d", [], 0.012, 0.006)
    print(f"3-D: p_in / (2 sigma / R) = {jump:.4f}, max |u| / (sigma / eta) = {spurious:.2e}")
    assert abs(jump - 1.0) < 0.05
    assert spurious < 1e-2


def test_square_drop_becomes_a_circle():
    """A 2 mm square relaxes to the disc of the same area: radius L / sqrt(pi) within 2 %
    (from the second moment, R = sqrt(2 <r^2>), which is L / sqrt(3) for the square), and
    the outermost particles lie on a circle (spread of their radii < 3 % of R)."""
    _, cfg = load_case(CASES / "static_drop_2d", ["scene.shape=\"box\"", "scene.dx_m=1e-4",
                                                   "run.t_end_s=0.012", "numerics.damping_time_s=0.012"])
    scene, sim = make_simulation(cfg)
    L = scene.info["side"]
    run_steps(sim, t_end=0.012)
    x = sim.state.x - sim.state.x.mean(0)
    r = x.norm(dim=-1)
    R_moment = math.sqrt(2.0 * float((r * r).mean()))
    R_exact = L / math.sqrt(math.pi)
    surf = sim.surface.normal.norm(dim=-1) > 0
    ang = torch.atan2(x[:, 1], x[:, 0])
    bins = torch.floor((ang + math.pi) / (2 * math.pi) * 36).long()
    outer = torch.zeros(36, dtype=r.dtype).scatter_reduce(0, bins, r, "amax")
    spread = float(outer.std() / outer.mean())
    print(f"R_moment / (L / sqrt(pi)) = {R_moment / R_exact:.4f}, outer-radius spread {spread:.3%}, "
          f"surface particles {int(surf.sum())}")
    assert abs(R_moment / R_exact - 1.0) < 0.02
    assert spread < 0.03


def flat_slab(T_of_xy, n=(12, 12, 8), dx=1e-4, dtype=torch.float64):
    """A slab periodic in x and y: fluid on top of 4 wall layers, temperature T(x, y)."""
    x = lattice(n, dx, origin=(0.0, 0.0, -n[2] * dx), dtype=dtype)
    wall = x[:, 2] < -(n[2] - 4) * dx
    phase = torch.where(wall, torch.full((x.shape[0],), int(Phase.WALL)), torch.full((x.shape[0],), int(Phase.FLUID)))
    st = ParticleState.create(x, torch.zeros_like(x), 7890.0, 7890.0 * dx**3, phase.to(torch.int8),
                              T=T_of_xy(x[:, 0], x[:, 1]), dtype=dtype)
    dom = Domain([0.0, 0.0, -n[2] * dx], [n[0] * dx, n[1] * dx, 0.0], [True, True, False])
    return st, dom


def test_recoil_integrates_to_vapour_pressure_times_area():
    """On a flat heated surface the recoil force sums to int p_v(T) dA (within 2 %; the
    CSF delta normalisation makes it exact to round-off on a lattice) and points into the melt."""
    from torchsph.core.neighbors import build_table

    dx, n = 1e-4, (12, 12, 8)
    Lx, Ly = n[0] * dx, n[1] * dx
    losses = SurfaceLosses(evaporation=True)
    kernel = make_kernel("wendland_c2", 3)
    h = 1.5 * dx
    for name, Tfun in [("uniform 3200 K", lambda x, y: torch.full_like(x, 3200.0)),
                       ("hot spot", lambda x, y: 2500.0 + 900.0 * torch.sin(math.pi * x / Lx) ** 2
                        * torch.sin(math.pi * y / Ly) ** 2)]:
        st, dom = flat_slab(Tfun, n, dx)
        sf = SurfaceForces(SurfaceParams(recoil=True), kernel, h, dom, 1.5, losses.vapour_pressure)
        nb, mask = build_table(st.x, kernel.radius(h), dom)
        sf.select_pairs(st, NeighbourTable.dense(nb, mask))
        a = sf.accelerations(st)
        F = (a * st.m.unsqueeze(-1)).sum(0)
        xc = lattice(n[:2], dx, dtype=torch.float64)
        exact = float((losses.vapour_pressure(Tfun(xc[:, 0], xc[:, 1])) * dx * dx).sum())
        print(f"{name}: sum F_z = {float(F[2]):.6g} N, -int p_v dA = {-exact:.6g} N")
        assert abs(float(-F[2]) / exact - 1.0) < 0.02
        assert abs(float(F[0])) < 1e-9 * exact and abs(float(F[1])) < 1e-9 * exact


def test_capillary_limit_binds_and_a_fixed_dt_above_it_is_refused():
    """The capillary limit 0.25 sqrt(rho h^3 / (2 pi alpha)) enters the automatic step, and a
    fixed dt above it is refused with the limit named."""
    over = ["scene.dx_m=1e-4", "fluid.c0_m_s=0.5", "surface.tension_N_m=5.0"]
    _, cfg = load_case(CASES / "static_drop_2d", over)
    _, sim = make_simulation(cfg)
    h = 1.5e-4
    expect = 0.25 * math.sqrt(float(sim.state.rho.min()) * h**3 / (2 * math.pi * 5.0))
    assert sim.limits()["capillary"] == pytest.approx(expect, rel=1e-12)
    assert sim.choose_dt()[1] == "capillary"
    _, cfg = load_case(CASES / "static_drop_2d", over + [f"numerics.dt_s={2 * expect}"])
    with pytest.raises(SimulationError, match="capillary limit"):
        make_simulation(cfg)


@pytest.mark.parametrize("text,match", [
    ("[surface]\ntension_N_m = -1.0\n", "tension_N_m = -1.0"),
    ("[surface]\ntension = 1.0\n", "unknown key \\[surface\\] tension"),
    ("[surface]\nrecoil = true\n", "recoil = true needs a \\[thermal\\] section"),
    ("[surface]\nmarangoni = true\n", "declares no force"),
])
def test_surface_case_errors(tmp_path, text, match):
    base = (CASES / "static_drop_2d" / "case.toml").read_text().split("[surface]")[0]
    rest = (CASES / "static_drop_2d" / "case.toml").read_text().split("[numerics]")[1]
    (tmp_path / "case.toml").write_text(base + text + "\n[numerics]" + rest)
    with pytest.raises(CaseError, match=match):
        load_case(tmp_path)


def test_oscillating_drop_mode2_period():
    """Mode-2 oscillation of a 2-D drop, R = 15 dx: period within 5 % of Rayleigh's
    2 pi / sqrt(6 sigma / (rho R^3)) (measured +3.5 %; R = 10 dx: +7.4 %, R = 20 dx: +1.4 %)."""
    _, cfg = load_case(CASES / "oscillating_drop_2d", ["scene.dx_m=6.6667e-5"])
    scene, sim = make_simulation(cfg)
    R, sigma, rho = scene.info["R"], cfg["surface"]["tension_N_m"], cfg["fluid"]["rho0_kg_m3"]
    period = 2 * math.pi / math.sqrt(6 * sigma / (rho * R**3))
    ts, ys = [], []

    def cb(sim, info):
        x = sim.state.x - sim.state.x.mean(0)
        ts.append(sim.t)
        ys.append(float((x[:, 0] ** 2 - x[:, 1] ** 2).mean()))

    run_steps(sim, t_end=cfg["run"]["t_end_s"], callback=cb)
    mean = sum(ys) / len(ys)
    ys = [y - mean for y in ys]
    zc = [ts[i] - ys[i] * (ts[i + 1] - ts[i]) / (ys[i + 1] - ys[i])
          for i in range(len(ys) - 1) if ys[i] * ys[i + 1] < 0]
    assert len(zc) >= 4, zc
    measured = 2 * (zc[-1] - zc[1]) / (len(zc) - 2)
    print(f"period {measured * 1e3:.3f} ms, Rayleigh {period * 1e3:.3f} ms ({measured / period - 1:+.2%})")
    assert abs(measured / period - 1) < 0.05


def birikh_layer(n_depth=10, t_end=0.008):
    """The thermocapillary layer of cases/thermocapillary_layer_2d with the surface tilt of
    the steady return flow built in (deeper at the cold end) and T = T0 + G x held."""
    from torchsph.scenes.builders import build_scene, tait_density

    _, cfg = load_case(CASES / "thermocapillary_layer_2d", [f"scene.n_depth={n_depth}"])
    G, T0 = 4000.0, 300.0
    fl = cfg["fluid"]
    mu, d, L = fl["viscosity_Pa_s"], cfg["scene"]["fluid_depth_m"], cfg["scene"]["fluid_width_m"]
    rho0, g = fl["rho0_kg_m3"], -fl["gravity_m_s2"][1]
    tau = abs(cfg["surface"]["dtension_dT_N_mK"]) * G
    scene = build_scene(cfg)
    st = scene.state
    fluid = st.phase == Phase.FLUID
    f = 1.0 - 3 * tau / (2 * d * rho0 * g) * (st.x[:, 0] - L / 2) / d  # dp/dx = 3 tau / (2 d)
    st.x[fluid, 1] = st.x[fluid, 1] * f[fluid]
    st.rho = torch.where(fluid, tait_density(rho0 * g * (d * f - st.x[:, 1]), fl), st.rho)
    _, sim = make_simulation(cfg, scene=scene)

    def hold(sim, info=None):
        sim.state.T = T0 + G * sim.state.x[:, 0]

    hold(sim)
    run_steps(sim, t_end=t_end, callback=hold)
    s = sim.state
    mid = (s.phase == Phase.FLUID) & ((s.x[:, 0] - L / 2).abs() < 0.5e-3)
    return s.x[mid, 1] / d, s.v[mid, 0] / (-tau * d / (4 * mu))


def test_thermocapillary_return_flow_birikh():
    """Imposed surface gradient, closed ends, 10 layers, steady (t = 16 ms: the surface tilt
    settles with a time scale mu L^2 / (rho g d^3) = 3 ms): the mid-length profile fitted by
    u = U (a z/d + b (z/d)^2) (no slip at the bottom) has the Birikh shape b / -a = 3/2 and
    the surface speed U (a + b) = tau d / (4 mu), both within 5 % (measured -0.6 % and
    +0.3 %; 20 layers at 12 ms: +0.5 % and +0.3 %; at 8 ms, not yet steady: -7 %)."""
    z, u = birikh_layer(t_end=0.016)
    A = torch.stack([z, z * z], 1)
    a, b = torch.linalg.lstsq(A, u.unsqueeze(1)).solution.squeeze(1).tolist()
    print(f"fit u/U = {a:.3f} z/d + {b:.3f} (z/d)^2 (Birikh: -2, 3); surface speed {a + b:.3f} U")
    assert abs(b / -a - 1.5) < 0.075
    assert abs(a + b - 1.0) < 0.05


def test_blow_up_above_the_capillary_limit_is_diagnosed():
    """A drop stepped at 8x the acoustic limit (2.3x the capillary one) blows up within a
    few steps; the one-line diagnosis names the particle, the surface-tension term and the
    limits the step exceeded (scripts/tools/stress.py: stable up to 4x, i.e. 1.1x capillary)."""
    assert_blow_up_diagnosed("oscillating_drop_2d", ["scene.dx_m=1e-4"], "acoustic", 8, 50,
                             ("blow-up at step", "particle id", "largest term there: surface_tension",
                              "capillary x"))


def test_zero_net_force_keeps_a_thermocapillary_drop_in_place():
    """A free 2-D drop with a vertical temperature gradient (100 K/mm, alpha' = -2e-4 N/(m K)):
    the continuum surface forces (tension with alpha(T) plus Marangoni) have no resultant on
    the closed surface, the discrete ones keep one (measured 5.1e-3 N/m, 8 % of the tangential total alpha' G R pi),
    which accelerates the whole drop. ``surface.zero_net_force`` removes it: the centre of
    mass stays at rest to round-off, while the circulation is the same to 10 %."""
    out = {}
    for z in ("false", "true"):
        _, cfg = load_case(CASES / "static_drop_2d", ["surface.dtension_dT_N_mK=-2e-4", "numerics.damping_time_s=0.0",
                                                     "scene.dx_m=0.1e-3", f"surface.zero_net_force={z}"])
        scene, sim = make_simulation(cfg)
        s = sim.state
        s.T = 300.0 + 1e5 * (s.x[:, 1] - s.x[:, 1].mean())
        sim.dvdt = sim.accelerations(s.v)
        run_steps(sim, t_end=0.003)
        s = sim.state
        u_com = (s.m.unsqueeze(-1) * s.v).sum(0) / s.m.sum()
        out[z] = (float(u_com.norm()), float((s.v - u_com).norm(dim=-1).max()))
    assert out["false"][0] > 1e-3  # the discrete forces' resultant: mm/s after 3 ms
    assert out["true"][0] < 1e-12
    assert abs(out["true"][1] / out["false"][1] - 1) < 0.1


def test_one_colour_gradient_per_step_for_the_surface_forces_and_the_losses(monkeypatch):
    """A cube of melt with surface tension and the evaporation loss reads the colour gradient
    in two terms (the forces on its surface, the losses' area on every surface particle): the
    free-surface stage evaluates it once per step, counted on the pair sum itself, on plain
    steps and on steps with a neighbour rebuild (where the losses' area of the rows that moved
    is made afresh: the one evaluation then covers those rows too; before, a second one). That the values
    are those of separate evaluations: the runs before and after this stage agree bit for bit."""
    from pathlib import Path

    from torchsph.physics.free_surface import colour_and_norm_pairs, colour_gradient_pairs

    root = Path(__file__).resolve().parents[1]
    _, cfg = load_case(root / "cases" / "cube_evaporation_preview", ["scene.size_m=[2.5e-3, 2.5e-3, 2.5e-3]",
                                                                                "scene.temperature_K=1800.0"])
    _, sim = make_simulation(cfg)
    stage = sim.surface_model.colour
    assert sim.thermal.colour is stage and sim.thermal.losses.active
    calls = []

    def counted(*a):
        calls.append(a[3].numel())
        return colour_gradient_pairs(*a)

    fused = []

    def counted_norm(*a):  # the stage's pair sum when it also makes zeta (a rebuild's rows)
        calls.append(a[3].numel())
        fused.append(len(calls))
        return colour_and_norm_pairs(*a)

    stage.fn = counted  # the stage's pair sum, and the one the losses would call on their own
    monkeypatch.setattr("torchsph.physics.losses.colour_gradient_pairs", counted)
    monkeypatch.setattr("torchsph.physics.free_surface.colour_and_norm_pairs", counted_norm)
    per_step, rebuilt, rows = [], [], []
    for k in range(10):
        if k in (3, 7):
            sim.stale = True  # a rebuild in this step: the losses' area is evaluated afresh
        builds, n0 = sim.nl.n_builds, len(calls)
        sim.advance()
        rebuilt.append(sim.nl.n_builds > builds)
        per_step.append(len(calls) - n0)
        rows.append(calls[-1])
        assert sim.thermal.area_cache is not None or k == 0  # (step 0 re-selects after the area)
    # (step 0 melts the block, which re-selects the pairs: the melt's first evaluation)
    assert sim.n_fluid == sim.state.n and per_step[1:] == [1] * 9 and rebuilt[3] and rebuilt[7]
    assert rows[3] == rows[7] == sim.state.n  # the union: the losses' rows with the melt's
