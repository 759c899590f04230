"""Absorbed beam power (2.7) with shadowing: eta0 Q0 on surfaces that cover the spot."""
import math

import pytest
import torch

from torchsph.physics.beam import Beam, beam_power, beams_power, gaussian_fraction_in_strip, reachable
from torchsph.scenes.builders import lattice

Q0, ETA, R = 300.0, 0.85, 0.75e-3


def plate(nx, ny, nz, dx, tilt_deg=0.0):
    """A block of lattice particles centred on the origin, top face at z = 0, rotated by
    ``tilt_deg`` about the y axis."""
    x = lattice((nx, ny, nz), dx, origin=(-nx * dx / 2, -ny * dx / 2, -nz * dx), dtype=torch.float64)
    c, s = math.cos(math.radians(tilt_deg)), math.sin(math.radians(tilt_deg))
    rot = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=torch.float64)
    return x @ rot.T


def beam_at(azimuth_deg, aim=(0.0, 0.0, 0.0)):
    a = math.radians(azimuth_deg)
    return Beam(Q0, ETA, R, (math.sin(a), 0.0, -math.cos(a)), aim)


def total(x, beam, dx):
    P = beam_power(x, torch.ones(x.shape[0], dtype=torch.bool), beam, 0.0, dx)
    return float(P.sum()), P


def test_flat_plate_vertical_beam_within_1pct():
    dx = 1e-4
    x = plate(70, 70, 4, dx)
    P, per = total(x, beam_at(0.0), dx)
    assert P == pytest.approx(ETA * Q0, rel=0.01)
    # all power goes to the top layer: the layers below are in its shadow
    assert float(per[x[:, 2] < -dx].abs().sum()) == 0.0


def test_flat_plate_beam_at_45_within_1pct():
    dx = 1e-4
    x = plate(90, 70, 4, dx)
    P, _ = total(x, beam_at(45.0), dx)
    assert P == pytest.approx(ETA * Q0, rel=0.01)


@pytest.mark.parametrize("tilt", [20.0, -30.0])
def test_tilted_plate_beam_at_45_within_2pct(tilt):
    dx = 1e-4
    x = plate(110, 80, 5, dx, tilt_deg=tilt)
    P, _ = total(x, beam_at(45.0), dx)
    assert P == pytest.approx(ETA * Q0, rel=0.02)


def test_cylinder_wire_beam_at_45_within_2pct():
    """A vertical wire (d = 1.2 mm) intercepts the strip |a| < d/2 of the beam's Gaussian."""
    dx = 0.05e-3
    d = 1.2e-3
    n = round(d / dx)
    x = lattice((n, n, 140), dx, origin=(-d / 2, -d / 2, -3.5e-3), dtype=torch.float64)
    x = x[(x[:, 0] ** 2 + x[:, 1] ** 2) < (d / 2) ** 2]
    P, _ = total(x, beam_at(45.0), dx)
    assert P == pytest.approx(ETA * Q0 * gaussian_fraction_in_strip(d, R), rel=0.02)


def test_shadowed_particles_get_nothing():
    """A second plate hidden under the first absorbs no power."""
    dx = 1e-4
    top = plate(70, 70, 2, dx)
    below = plate(70, 70, 2, dx) - torch.tensor([0.0, 0.0, 1e-3], dtype=torch.float64)
    x = torch.cat([top, below])
    P, per = total(x, beam_at(0.0), dx)
    assert float(per[top.shape[0]:].sum()) == 0.0
    assert P == pytest.approx(ETA * Q0, rel=0.01)


def test_moving_aim_point():
    dx = 1e-4
    x = plate(100, 60, 2, dx)
    b = Beam(Q0, ETA, R, (0.0, 0.0, -1.0), (-2e-3, 0.0, 0.0), velocity=(0.015, 0.0, 0.0))
    P0 = beam_power(x, torch.ones(x.shape[0], dtype=torch.bool), b, 0.0, dx)
    P1 = beam_power(x, torch.ones(x.shape[0], dtype=torch.bool), b, 0.2, dx)  # aim moved 3 mm
    c0 = float((P0 * x[:, 0]).sum() / P0.sum())
    c1 = float((P1 * x[:, 0]).sum() / P1.sum())
    assert c0 == pytest.approx(-2e-3, abs=dx) and c1 == pytest.approx(1e-3, abs=dx)


def test_beam_heating_energy_bookkeeping_closes():
    """Heating a plate with a beam (latent heat on): absorbed power = eta0 Q0 within 1 % and
    stored energy = absorbed energy (the bookkeeping integrates exactly what the step does)."""
    from conftest import CASES

    from torchsph.io.config import load_case
    from torchsph.run.build import make_simulation
    from torchsph.step.loop import run_steps

    _, cfg = load_case(CASES / "beam_plate", ["run.t_end_s=0.02"])
    _, sim = make_simulation(cfg)
    run_steps(sim, t_end=0.02)
    e = sim.energy_balance()
    b = cfg["beam"][0]
    assert e["beam_J"] / sim.t == pytest.approx(b["efficiency"] * b["power_W"], rel=0.01)
    assert e["residual_rel"] < 1e-6
    assert float(sim.state.T.max()) > 1753.15  # the spot has melted (latent heat absorbed)


def test_beam_on_lattice_columns_at_bin_edges_keeps_its_power():
    """A vertical beam on a cube of odd particle count: lattice columns lie at whole
    multiples of dx from the axis, where bins aligned on the axis would split them by
    round-off and leave empty bins (-51 % of the power was lost before the bins were
    centred on the columns). Absorbed power = eta0 Q0 erf(L / (sqrt 2 r))^2 within 1e-4 (the
    midpoint rule over bins whose outer edges are the cube's edges: 6e-5 at n = 25)."""
    import math

    import torch

    from torchsph.physics.beam import Beam, beam_power
    from torchsph.scenes.builders import lattice

    for n in (25, 24, 20):
        L = 2.5e-3
        dx = L / n
        x = lattice((n, n, 6), dx, origin=(-L / 2, -L / 2, -6 * dx), dtype=torch.float64)
        b = Beam(300.0, 0.85, 0.75e-3, (0.0, 0.0, -1.0), (0.0, 0.0, 0.0))
        P = float(beam_power(x, torch.ones(x.shape[0], dtype=torch.bool), b, 0.0, dx).sum())
        exact = 0.85 * 300.0 * math.erf(L / (math.sqrt(2.0) * 0.75e-3)) ** 2
        assert abs(P / exact - 1.0) < 1e-4, (n, P / exact - 1.0)


def test_several_beams_traced_together_equal_each_traced_alone():
    """The beams of a scene are traced in one set of operations (each on its own rows and bins):
    the same power per particle as tracing each beam alone on its rows and summing, for beams
    of different radii and directions, one moving, on the rows of a subset of the particles;
    and each absorbs eta0 Q0 on the plate that covers its spot."""
    dx = 1.0e-4
    x = plate(70, 70, 4, dx)
    rows = torch.nonzero(x[:, 0] > -3.2e-3).squeeze(1)  # not every particle is a row
    beams = [beam_at(0.0), Beam(200.0, 0.8, 0.5e-3, (0.6, 0.0, -0.8), (0.8e-3, 0.4e-3, 0.0)),
             Beam(150.0, 0.7, 0.6e-3, (0.0, -0.5, -0.866), (-0.5e-3, 0.0, 0.0), velocity=(0.02, 0.0, 0.0))]
    t = 0.02  # the moving aim has gone 0.4 mm
    subs = reachable(beams, x.index_select(0, rows), 0.0)
    assert subs[2] is None and 0 < subs[1].numel() < rows.numel()
    together = beams_power(beams, x, t, dx, subs, rows)
    alone = torch.zeros(rows.numel(), dtype=x.dtype)
    one = lambda m: torch.ones(m, dtype=torch.bool)  # noqa: E731
    for b, sub in zip(beams, subs):
        sel = torch.arange(rows.numel()) if sub is None else sub
        alone.index_add_(0, sel, beam_power(x.index_select(0, rows.index_select(0, sel)), one(sel.numel()), b, t, dx))
    assert torch.allclose(together, alone, rtol=1e-13, atol=0.0)
    assert float(together.sum()) == pytest.approx(sum(b.efficiency * b.power for b in beams), rel=1e-2)


def block_on_offset_plate(dx=1e-4, n=70, m=12):
    """A 12-spacing block standing on a plate, its lattice offset by half a spacing in x and y."""
    block = lattice((m, m, m), dx, origin=(-m * dx / 2 + dx / 2, -m * dx / 2 + dx / 2, 0.5 * dx), dtype=torch.float64)
    return torch.cat([block, plate(n, n, 4, dx)]), block.shape[0]


def tilted_beam(azimuth, phi, power=Q0, aim=(0.0, 0.0, 0.0)):
    a, p = math.radians(azimuth), math.radians(phi)
    return Beam(power, ETA, R, (math.sin(a) * math.cos(p), math.sin(a) * math.sin(p), -math.cos(a)), aim)


@pytest.mark.parametrize("azimuth,phi", [(0.0, 0.0), (45.0, 0.0), (45.0, 90.0)])
def test_a_body_on_another_lattice_loses_none_of_the_beam(azimuth, phi):
    """A block standing on a plate with its lattice offset by half a spacing in x and y (as a
    wire over a substrate): the bins are centred on the block's column nearest the axis, so
    the plate's columns lie on bin edges and round-off sends some to the neighbouring bin,
    leaving empty bins inside the silhouette (-10 % of eta0 Q0 vertically, -7 % at 45 deg,
    before their power went to the lit bins around them). The plate covers the spot: the
    absorbed power is eta0 Q0 within 1e-6 (measured 2e-8), and the block, which stands in
    the spot, takes its part."""
    dx = 1e-4
    x, n_block = block_on_offset_plate(dx)
    P, per = total(x, tilted_beam(azimuth, phi), dx)
    assert P == pytest.approx(ETA * Q0, rel=1e-6)
    assert float(per[:n_block].sum()) > 0.1 * ETA * Q0


def test_beams_traced_together_fill_each_beams_holes_as_alone():
    """The holes' power is each beam's own (its own bin grid, its own Gaussian) when the beams
    of a scene are traced in one plan: the same power per particle as each beam alone, on the
    block over the half-offset plate, and eta0 Q0 each (a plan that took the first beam's bin
    centre for every beam's holes put the second's holes' power at the wrong intensities)."""
    dx = 1e-4
    x, _ = block_on_offset_plate(dx)
    # the second aimed 0.25 mm up the axis: its bins are centred 0.35 spacings off its axis, the
    # first's on it, and both have holes (2.4 and 18.7 W)
    beams = [tilted_beam(45.0, 90.0), tilted_beam(45.0, 270.0, 200.0, (0.0, 0.0, 0.25e-3)), tilted_beam(0.0, 0.0, 100.0)]
    together = beams_power(beams, x, 0.0, dx)
    alone = sum(total(x, b, dx)[1] for b in beams)
    assert torch.allclose(together, alone, rtol=1e-12, atol=1e-15)
    assert float(together.sum()) == pytest.approx(ETA * (Q0 + 200.0 + 100.0), rel=1e-6)
