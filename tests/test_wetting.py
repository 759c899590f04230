"""Wetting (SPEC 3b): a 2-D liquid cap on a plate settles at the contact angle it is given,
a cap at its equilibrium stays at rest, and the contact-line force's reaction on the solid
balances it to round-off."""
import math

import pytest
import torch
from conftest import CASES

from torchsph.core.state import Phase
from torchsph.io.config import CaseError, load_case
from torchsph.post import caps
from torchsph.post.caps import contact_angle, fit_sphere
from torchsph.run.build import make_simulation
from torchsph.step.loop import run_steps

torch.set_num_threads(1)  # these scenes are small: threads only add overhead

# sigma / eta = 1 m/s; the settling drag ends at 10 ms; dx = R / 15
COMMON = ["fluid.viscosity_Pa_s=0.05", "numerics.damping_time_s=0.01", "scene.dx_m=3.3333e-5"]


def settle(theta, theta0, radius, t_end=0.020, t_from=0.014):
    """The 2-D cap from ``theta0`` with theta_eq = ``theta``: the fitted contact angles (deg) and
    the melt's centre-of-mass speeds (m/s), every ms from ``t_from``."""
    r = caps.settle(CASES / "sessile_drop_2d", COMMON + [
        f"surface.contact_angle_deg={theta}", f"scene.initial_angle_deg={theta0}",
        f"scene.radius_m={radius}"], t_from, t_end)
    return r["angles"], r["speeds"]


@pytest.mark.parametrize("theta,theta0,radius", [(30.0, 45.0, 1e-3), (60.0, 75.0, 5e-4),
                                                 (90.0, 75.0, 5e-4), (120.0, 105.0, 5e-4)])
def test_sessile_drop_2d_settles_at_the_contact_angle(theta, theta0, radius):
    """A cap started 15 deg off theta_eq (30 and 60 deg spread, 90 and 120 deg draw in) settles
    at theta_eq within 5 deg: the mean of the fitted angle from 14 to 20 ms (after the settling
    drag ends at 10 ms), and every sample within 8 deg. (The 30 deg cap, R = 30 dx, is the thin
    one: 7 particles high.)"""
    angles, _ = settle(theta, theta0, radius)
    mean = sum(angles) / len(angles)
    print(f"theta_eq {theta}: from {theta0}, mean {mean:.2f}, samples {[round(a, 1) for a in angles]}")
    assert abs(mean - theta) < 5.0
    assert max(abs(a - theta) for a in angles) < 8.0


def settle_3d(theta, theta0, radius, dx, t_end=0.020, t_from=0.014, extra=()):
    """The 3-D cap of ``cases/sessile_drop_3d`` (settling drag to 10 ms): the fitted contact
    angles (deg) every ms from ``t_from``; ``extra``: more overrides."""
    return caps.settle(CASES / "sessile_drop_3d", [
        f"surface.contact_angle_deg={theta}", f"scene.initial_angle_deg={theta0}",
        f"scene.radius_m={radius}", f"scene.dx_m={dx}", *extra], t_from, t_end)["angles"]


@pytest.mark.slow
@pytest.mark.parametrize("theta,theta0,radius,per_dx,extra", [
    (30.0, 45.0, 1.5e-3, 24, ("scene.plate_width_m=4e-3",)),  # a thin cap: 6 dx high at R/24
    (60.0, 75.0, 5e-4, 8, ()), (90.0, 75.0, 5e-4, 8, ()),
    (120.0, 135.0, 5e-4, 8, ()),  # approached from above: the line advances
    (120.0, 105.0, 5e-4, 8, ())])  # from below: the line recedes
def test_sessile_drop_3d_settles_at_the_contact_angle(theta, theta0, radius, per_dx, extra):
    """3-D caps, dx = R/8 (30 deg: R/24; slow: ~5 min each, 30 deg ~14) started 15 deg off: the mean
    fitted angle over 14-20 ms within 5 deg of theta_eq (measured with the default band
    curvature, 'clear': 30 deg 34.4, 60 deg 63.2, 90 deg 86.1, 120 deg from 135: 121.0, from
    105: 123.0)."""
    angles = settle_3d(theta, theta0, radius, radius / per_dx, extra=extra)
    mean = sum(angles) / len(angles)
    print(f"3-D theta_eq {theta}: from {theta0}, mean {mean:.2f}, samples {[round(a, 1) for a in angles]}")
    assert abs(mean - theta) < 5.0


BESIDE_RECEDES = ("measured 107.4 deg at dx = R/8 (stop 30), 114.1 deg at R/12, 114.3 at R/16 (stops 48-49): "
                  "with the band's tension at the curvature of all the surface beside it, the flank's, "
                  "the pressure holds the foot out (stop 50): why the default is 'clear'")


@pytest.mark.slow
@pytest.mark.xfail(reason=BESIDE_RECEDES, strict=True)
def test_a_receding_3d_cap_stops_short_with_the_band_curvature_of_all_the_surface_beside_it():
    """The model before stop 51 (surface.band_curvature = 'beside'), kept as an option: the 3-D cap
    at 120 deg drawn in from 105 deg (dx = R/8, slow: ~5 min) stops 13 deg short (BESIDE_RECEDES);
    strict, so a change that makes it reach its angle is noticed."""
    angles = settle_3d(120.0, 105.0, 5e-4, 5e-4 / 8, extra=["surface.band_curvature=beside"])
    mean = sum(angles) / len(angles)
    print(f"3-D 120 from 105, band curvature beside: mean {mean:.2f}, samples {[round(a, 1) for a in angles]}")
    assert abs(mean - 120.0) < 5.0


def test_a_cap_at_its_contact_angle_stays_at_rest():
    """A 60 deg cap on a plate with no gravity, started at 60 deg: after the settling time its
    centre of mass moves at < 1e-3 of the capillary speed sigma / eta (no self-propulsion)."""
    angles, speeds = settle(60.0, 60.0, 5e-4, t_end=0.016, t_from=0.012)
    print(f"angles {[round(a, 1) for a in angles]}, centre-of-mass speeds {speeds}")
    assert max(speeds) < 1e-3 * (0.05 / 0.05)
    assert abs(sum(angles) / len(angles) - 60.0) < 5.0


def pillar(pin: bool, monkeypatch) -> tuple[list, float]:
    """A 30 deg liquid on a 2-D pillar as wide as the drop's half-disc start (R = 15 dx): the
    fitted angles every ms over 14-20 ms, and the fraction of the melt below the pillar's top
    at 20 ms. ``pin``: Gibbs's criterion at the edges (False: the blended normal alone)."""
    from torchsph.physics.wetting import ContactAngle

    monkeypatch.setattr(ContactAngle, "pin", pin)
    _, cfg = load_case(CASES / "sessile_drop_2d", COMMON + [
        "surface.contact_angle_deg=30.0", "scene.radius_m=5e-4", "scene.plate_width_m=1e-3", "run.t_end_s=0.02"])
    scene, sim = make_simulation(cfg)
    angles = []
    for k in range(7):
        run_steps(sim, t_end=0.014 + k * 1e-3)
        angles.append(contact_angle(sim.state, scene.dx)["angle_deg"])
    fl = sim.state.phase == Phase.FLUID
    below = float((sim.state.x[fl, -1] < -0.25 * scene.dx).to(torch.float64).mean())
    return angles, below


def test_a_drop_on_a_pillar_holds_at_its_edges(monkeypatch):
    """Gibbs's criterion: a drop whose 30 deg cap would be 4.2 R wide sits on a pillar 2 R wide.
    At the pillar's 90 deg edges the line may hold from 30 to 120 deg, so the half disc stays a
    half disc: its angle over 14-20 ms within 5 deg of 90 deg (every sample within 8), and < 2 %
    of the melt below the pillar's top (measured: 84.7-88.4 deg, 1.1 %). Without the criterion
    (the blended normal alone) the melt runs over the edges: measured 6 % below the top at
    20 ms and the angle wandering from 79 to 99 deg, which this test must reject."""
    angles, below = pillar(True, monkeypatch)
    mean = sum(angles) / len(angles)
    print(f"pinned: angles {[round(a, 1) for a in angles]}, mean {mean:.2f}, below the top {below:.4f}")
    assert abs(mean - 90.0) < 5.0 and max(abs(a - 90.0) for a in angles) < 8.0
    assert below < 0.02
    angles, below = pillar(False, monkeypatch)
    print(f"blended normal: angles {[round(a, 1) for a in angles]}, below the top {below:.4f}")
    assert below > 0.03 or max(abs(a - 90.0) for a in angles) > 8.0


def test_the_wetting_force_and_its_reaction_sum_to_zero():
    """The contact-line force on the melt (spread over the melt near the line) and its reaction
    booked on the plate sum to zero to round-off, in each direction, on a cap that is not at
    its angle (the force is not small); the reaction sits on plate particles only."""
    _, cfg = load_case(CASES / "sessile_drop_2d", COMMON + ["surface.contact_angle_deg=30.0"])
    scene, sim = make_simulation(cfg)
    run_steps(sim, steps=50)
    _, parts = sim.surface.accelerations(sim.state, terms=True)
    s = sim.state
    F = s.m.unsqueeze(-1) * parts["contact_line"]
    R = sim.surface.wetting.reaction
    scale = float(F.abs().sum())
    assert scale > 0
    fluid = s.phase == Phase.FLUID
    assert float(R[fluid].abs().max()) == 0.0 and float(F[~fluid].abs().max()) == 0.0
    total = (F.sum(0) + R.sum(0)).abs().max()
    print(f"sum |F| = {scale:.3e} N/m, |sum F + sum R| = {float(total):.2e}")
    assert float(total) < 1e-13 * scale
    # the line is pulled outwards (30 deg < 90 deg): each side's force points away from the axis
    right = fluid & (s.x[:, 0] > 0)
    assert float(F[right, 0].sum()) > 0 and float(F[fluid & (s.x[:, 0] < 0), 0].sum()) < 0


def test_contact_angle_fit_recovers_a_lattice_cap():
    """The measurement: a lattice cap cut at 60 deg (R = 20 dx) reads 60 deg within 2 deg; the
    sphere fit is exact on points of a circle."""
    _, cfg = load_case(CASES / "sessile_drop_2d", ["scene.initial_angle_deg=60.0"])
    scene, _ = make_simulation(cfg)
    ca = contact_angle(scene.state, scene.dx)
    assert abs(ca["angle_deg"] - 60.0) < 2.0, ca
    phi = torch.linspace(0.1, 3.0, 40, dtype=torch.float64)
    pts = torch.stack([1.0 + 2.0 * torch.cos(phi), -0.5 + 2.0 * torch.sin(phi)], dim=1)
    c, R = fit_sphere(pts)
    assert abs(R - 2.0) < 1e-12 and float((c - torch.tensor([1.0, -0.5], dtype=torch.float64)).abs().max()) < 1e-12


@pytest.mark.parametrize("over,match", [
    (["surface.contact_angle_deg=180.0"], r"contact_angle_deg"),
    (["surface.contact_angle_deg=0.0"], r"contact_angle_deg"),
    (["scene.radius_m=5e-5"], r"radius_m"),
    (["scene.plate_width_m=2e-4"], r"plate_width_m"),
])
def test_wetting_case_errors(over, match):
    with pytest.raises(CaseError, match=match):
        load_case(CASES / "sessile_drop_2d", over)


def test_circular_cap_relations():
    """SPEC 3b's numbers: A = 2.26 mm^2 at 30 deg gives W 5.00 / H 0.67 mm, at 90 deg 2.40 / 1.20."""
    from torchsph.core.analytic import circular_cap

    c30 = circular_cap(2.26e-6, math.radians(30.0), 2)
    c90 = circular_cap(2.26e-6, math.radians(90.0), 2)
    assert c30["W"] == pytest.approx(5.00e-3, abs=0.01e-3) and c30["H"] == pytest.approx(0.67e-3, abs=0.01e-3)
    assert c90["W"] == pytest.approx(2.40e-3, abs=0.01e-3) and c90["H"] == pytest.approx(1.20e-3, abs=0.01e-3)
    v = circular_cap(4.0 / 3.0 * math.pi, math.radians(90.0), 3)  # a hemisphere of radius 2^(1/3)
    assert v["R"] == pytest.approx(2.0 ** (1.0 / 3.0), rel=1e-12)


def test_wetting_false_is_the_model_without_an_angle(tmp_path):
    """``surface.wetting = false`` runs the thesis's model (c = 1 in melt and solid) although the
    case states an angle: 40 steps of a spreading cap equal, bit for bit, the same cap from a
    case file without the angle, and differ from the cap with the angle (the force acts)."""
    over = ["scene.initial_angle_deg=90", "numerics.damping_time_s=0.0", "scene.dx_m=5e-5"]

    def run(case, extra=()):
        _, cfg = load_case(case, over + list(extra))
        _, sim = make_simulation(cfg)
        run_steps(sim, steps=40)
        return sim.state.x

    text = (CASES / "sessile_drop_2d" / "case.toml").read_text()
    assert "contact_angle_deg" in text  # the case states one
    (tmp_path / "case.toml").write_text("\n".join(line for line in text.splitlines()
                                                  if not line.startswith("contact_angle_deg")))
    off = run(CASES / "sessile_drop_2d", ["surface.wetting=false"])
    assert torch.equal(off, run(tmp_path))
    assert not torch.equal(off, run(CASES / "sessile_drop_2d"))


def test_a_settling_study_continues_from_its_checkpoint(tmp_path):
    """A fine cap runs in legs (``caps.settle(..., checkpoint=)``): a run stopped at 3 ms and
    continued to 4 ms from its checkpoint samples what one run to 4 ms samples: the centre-of-
    mass speeds bit for bit, the fitted angles to round-off (the fit's own 1e-12 deg); the
    samples taken before the stop are carried in the checkpoint, not taken again."""
    over = COMMON + ["scene.dx_m=4e-5", "surface.contact_angle_deg=60", "scene.initial_angle_deg=75",
                     "scene.radius_m=5e-4"]
    whole = caps.settle(CASES / "sessile_drop_2d", over, 0.002, 0.004)
    ck = tmp_path / "cap.pt"
    first = caps.settle(CASES / "sessile_drop_2d", over, 0.002, 0.003, checkpoint=ck)
    assert len(first["angles"]) == 2 and ck.exists()
    legs = caps.settle(CASES / "sessile_drop_2d", over, 0.002, 0.004, checkpoint=ck)
    assert len(legs["angles"]) == len(whole["angles"]) == 3
    assert legs["speeds"] == whole["speeds"]
    assert max(abs(a - b) for a, b in zip(legs["angles"], whole["angles"])) < 1e-9
