"""The pendant drop (thesis §5.1, SPEC 3b): the gravity ramp it is loaded with moves a free
body exactly as the analytic ramp does; Tate's law with the Harkins-Brown factor, and the
cut that tells a fallen drop from the one still hanging; the scene's case errors."""
import math

import pytest
import torch
from conftest import CASES

from torchsph.core.analytic import HARKINS_BROWN, harkins_brown, tate_mass
from torchsph.core.state import Phase
from torchsph.io.config import CaseError, load_case
from torchsph.post.caps import fallen_mass
from torchsph.run.build import make_simulation
from torchsph.scenes.builders import build_scene
from torchsph.step.loop import run_steps

torch.set_num_threads(1)


def test_gravity_ramp_moves_the_centre_of_mass_as_the_analytic_ramp():
    """A periodic Taylor-Green box under gravity ramped over T: internal forces sum to zero, so
    the centre of mass moves with v = -g t^2 / (2 T) up to T and -g (t - T / 2) after; the
    kick-drift-kick's trapezoid is exact on a linear ramp: to round-off (1e-9)."""
    g, T = 2.0, 0.05
    _, cfg = load_case(CASES / "taylor_green_2d", ["scene.nx=20", f"fluid.gravity_m_s2=[0.0, {-g}]",
                                                   f"fluid.gravity_ramp_s={T}"])
    _, sim = make_simulation(cfg)
    s = sim.state
    v0 = float((s.m * s.v[:, 1]).sum() / s.m.sum())
    for t_end in (0.6 * T, T, 1.5 * T):
        run_steps(sim, t_end=t_end)
        t = sim.t
        exact = -g * t * t / (2 * T) if t <= T else -g * (t - T / 2)
        v = float((s.m * sim.state.v[:, 1]).sum() / s.m.sum()) - v0
        assert abs(v - exact) < 1e-9 * g * T, (t, v, exact)
    # without the ramp the same box accelerates at g from the start
    _, cfg = load_case(CASES / "taylor_green_2d", ["scene.nx=20", f"fluid.gravity_m_s2=[0.0, {-g}]"])
    _, sim = make_simulation(cfg)
    run_steps(sim, t_end=0.6 * T)
    v = float((sim.state.m * sim.state.v[:, 1]).sum() / sim.state.m.sum()) - v0
    assert abs(v + g * sim.t) < 1e-9 * g * T


def test_harkins_brown_table_and_tate_mass():
    """f at the table's rows, linear between them, an error outside it; tate_mass solves
    m g = 2 pi r sigma f(r / (m / rho)^(1/3)) (its fixed point) and, for f = 1, would be
    Tate's plain 2 pi r sigma / g."""
    for psi, f in HARKINS_BROWN:
        assert harkins_brown(psi) == pytest.approx(f, abs=1e-12)
    assert harkins_brown(0.85) == pytest.approx(0.5999, abs=1e-12)
    assert min(f for _, f in HARKINS_BROWN) == pytest.approx(0.5998)  # the curve's flat minimum
    with pytest.raises(ValueError, match="outside the Harkins-Brown table"):
        harkins_brown(1.5)
    r, sigma, g, rho = 0.5e-3, 0.05, 37.5, 1000.0
    m, f = tate_mass(r, sigma, g, rho)
    assert m * g == pytest.approx(2 * math.pi * r * sigma * harkins_brown(r / (m / rho) ** (1 / 3)), rel=1e-10)
    assert 0.6 < f < 0.73 and m < 2 * math.pi * r * sigma / g


def test_fallen_mass_cuts_at_the_highest_gap():
    """Two blobs 3 dx apart: the lower one's mass (satellites below count too); one blob with a
    stray particle below it, or blobs closer than 2 dx: nothing has fallen."""
    dx = 1.0
    upper = torch.arange(10, dtype=torch.float64)  # z = 0..9
    lower = -4.0 - torch.arange(6, dtype=torch.float64)  # z = -4..-9: a gap of 4 dx
    sat = torch.tensor([-13.0])  # a satellite 4 dx further down
    z = torch.cat([upper, lower, sat])
    m = torch.ones_like(z)
    fallen, cut = fallen_mass(z, m, dx)
    assert fallen == 7.0 and cut == pytest.approx(-2.0)
    stray = torch.cat([upper, torch.tensor([-5.0])])
    assert fallen_mass(stray, torch.ones_like(stray), dx) == (0.0, None)
    close = torch.cat([upper, -1.5 - torch.arange(6, dtype=torch.float64)])
    assert fallen_mass(close, torch.ones_like(close), dx)[1] is None


def test_pendant_drop_scene_wets_the_whole_end_face():
    """The drop's top layer lies one spacing below the wire's bottom layer and covers the end
    face: every wire particle of the bottom layer has drop particles straight below it."""
    _, cfg = load_case(CASES / "pendant_drop", ["scene.dx_m=1.25e-4"])
    sc = build_scene(cfg)
    s = sc.state
    drop, wire = s.x[s.phase == Phase.FLUID], s.x[s.phase == Phase.WALL]
    dx = sc.dx
    assert float(wire[:, 2].min()) - float(drop[:, 2].max()) == pytest.approx(dx)
    top = drop[drop[:, 2] > drop[:, 2].max() - 1e-12]
    bottom = wire[wire[:, 2] < wire[:, 2].min() + 1e-12]
    assert top.shape[0] >= bottom.shape[0]
    d = torch.cdist(bottom[:, :2], top[:, :2]).min(1).values
    assert float(d.max()) < 1e-6 * dx
    assert sc.info["mass"] == pytest.approx(float(s.m[s.phase == Phase.FLUID].sum()))


@pytest.mark.parametrize("over,key", [(["scene.wire_diameter_m=4e-4"], "wire_diameter_m"),
                                      (["scene.radius_m=3e-4"], "radius_m"),
                                      (["scene.wire_length_m=2e-4"], "wire_length_m")])
def test_pendant_drop_case_errors_name_the_key(over, key):
    with pytest.raises(CaseError, match=key):
        load_case(CASES / "pendant_drop", over)


@pytest.mark.slow
@pytest.mark.parametrize("liquid,d_wire,extra", [
    ("water-like", 1.5e-3, ()), ("steel", 1.2e-3, ()),  # measured -1.5 % and +0.8 %
    pytest.param("steel", 1.2e-3, ("surface.band_curvature=beside",), id="steel-beside")])  # measured -0.3 %
def test_pendant_drop_falls_at_tate_harkins_brown(liquid, d_wire, extra):
    """Tate's law with the Harkins-Brown factor (slow: ~9 and ~11 min): the drop (R = 1 mm,
    alpha = sigma, dx = 0.125 mm, 60 deg on the wire, gravity ramped as PENDANT_LIQUIDS says)
    necks in the liquid (less than 90 % of it falls) and the falling mass m obeys
    m g = 2 pi r sigma f(r / V^(1/3)) within 10 % at the load g it falls at (measured -1.5 %
    and +0.8 %; with the band curvature 'beside' -2.2 % and -0.3 %). This holds at these
    loading rates: over a 0.2 s ramp the water-like drop held to a 30 % higher load and fell
    21.6 % heavy. The 1 and 1.2 mm water-like drops peel off the
    wire's face whole and fall 17-25 % heavy, which this test would reject
    (docs/VERIFICATION.md, section 5.1)."""
    from torchsph.post.caps import PENDANT_LIQUIDS, detach

    liq = PENDANT_LIQUIDS[liquid]
    r = detach(CASES / "pendant_drop", liq["over"] + ["scene.dx_m=1.25e-4", f"scene.wire_diameter_m={d_wire}",
                                                      f"surface.tension_N_m={liq['sigma']}", *extra])
    assert r["detached"]
    m_tate, _ = tate_mass(d_wire / 2, liq["sigma"], r["g"], liq["rho"])
    print(f"{liquid}, d = {d_wire}: fell {r['m_fallen']:.4g} of {r['m_drop']:.4g} kg at g = {r['g']:.1f}; "
          f"Tate-H-B {m_tate:.4g}")
    assert r["m_fallen"] < 0.9 * r["m_drop"]
    assert abs(r["m_fallen"] / m_tate - 1.0) < 0.10
