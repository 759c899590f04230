"""The term protocol (torchsph/terms): a term a case names is built and evaluated at its
hooks, and its per-particle arrays travel with the particles."""
import pytest
import torch
from conftest import CASES

from torchsph.core.state import Array
from torchsph.io import checkpoint as ckpt
from torchsph.io.config import load_case
from torchsph.physics.terms import TERMS, Term, register
from torchsph.run.build import make_simulation
from torchsph.step import particles
from torchsph.step.loop import run_steps


def test_a_terms_per_particle_arrays_travel_with_the_particles(tmp_path, monkeypatch):
    """The array registry carries a term's own per-particle arrays: in particle_arrays,
    through a checkpoint and its restore, and through particle removal (a term made here,
    registered for this test only, that counts each particle's heat-evaluations)."""
    class Tally(Term):
        section = "tally"
        writes = ("heat",)
        ARRAYS = {"count": Array("heat evaluations")}

        @classmethod
        def from_case(cls, cfg, ctx):
            return cls()

        def select(self, sim):
            if getattr(self, "count", None) is None or self.count.shape[0] != sim.state.n:
                self.count = torch.zeros(sim.state.n, dtype=torch.long)

        def heat(self, sim, t, rows):
            self.count.index_add_(0, rows, torch.ones_like(rows))
            return torch.zeros(rows.numel(), dtype=sim.state.dtype)


    monkeypatch.setitem(TERMS, "tally", Tally)
    _, cfg = load_case(CASES / "radiating_slab")
    cfg["tally"] = {}
    _, sim = make_simulation(cfg)
    run_steps(sim, steps=3)
    arr = sim.particle_arrays()
    assert torch.equal(arr["tally.count"], sim.terms[-1].count) and int(arr["tally.count"].max()) == 4  # set-up + 3 steps
    ckpt.save(sim, tmp_path / "c.pt", ckpt.config_hash(cfg))
    _, sim2 = make_simulation(cfg)
    ckpt.restore(sim2, ckpt.load(tmp_path / "c.pt"), cfg)
    assert torch.equal(sim2.terms[-1].count, sim.terms[-1].count)
    keep = torch.arange(sim.state.n) % 2 == 0
    particles.set_particle_arrays(sim, {k: v[keep] for k, v in sim.particle_arrays().items()
                                        if v.shape[0] == keep.numel()})
    assert sim.terms[-1].count.shape[0] == int(keep.sum())


def test_a_term_must_name_its_section_and_write_only_known_rates():
    class Nameless(Term):
        writes = ("heat",)

    class Odd(Term):
        section = "odd"
        writes = ("pressure",)
    for cls in (Nameless, Odd):
        with pytest.raises(TypeError, match="a term needs a section and writes rates"):
            register(cls)
    assert "odd" not in TERMS


def test_a_force_term_drives_a_channel_like_the_fluids_own_body_force(monkeypatch):
    """The momentum hook: a term adding the acceleration F to every fluid particle drives
    the Poiseuille channel as the fluid's body_force_m_s2 = F does (the same sums in another
    order: equal to 1e-12 after 40 steps)."""
    class Push(Term):
        section = "push"
        writes = ("acceleration",)

        @classmethod
        def from_case(cls, cfg, ctx):
            return cls()

        def acceleration(self, sim, v):
            rows = sim.fluid.rows_f
            F = torch.tensor([8.0e-3, 0.0], dtype=sim.state.dtype)
            return rows, F.expand(rows.numel(), 2)

    monkeypatch.setitem(TERMS, "push", Push)
    _, ref_cfg = load_case(CASES / "poiseuille_2d")
    _, ref = make_simulation(ref_cfg)
    run_steps(ref, steps=40)
    _, cfg = load_case(CASES / "poiseuille_2d", ["fluid.body_force_m_s2=[0.0, 0.0]"])
    cfg["push"] = {}
    _, sim = make_simulation(cfg)
    run_steps(sim, steps=40)
    assert [type(t).__name__ for t in sim.force_terms] == ["Push"] and sim.t == ref.t
    scale = float(ref.state.v.abs().max())
    assert scale > 0 and float((sim.state.v - ref.state.v).abs().max()) < 1e-12 * scale


def test_solid_contact_keeps_melt_out_of_the_solids_spacing():
    """[solid_contact] (torchsph/physics/terms/contact.py) on the small deposition scene, 300 steps
    with melt beside the substrate and the wire: without it the melt creeps into the solid's
    lattice (its nearest solid particle comes to < 0.85 dx), with the spring (approach_over_c0
    = 0) no melt particle comes within 0.95 dx of solid at any sampled step, with the cases'
    force against approach only none within 0.9 dx; it acts only closer than r0 = dx (a melt
    particle at a lattice spacing feels nothing) and brings its time-step limit only while
    melt is near solid."""
    from test_deposition import small

    from torchsph.physics.terms.contact import SolidContact

    base = ("scene.source_power_W=300.0", "scene.wire_feed_m_s=0.3", "scene.wire_gap_m=3.0e-3")
    closest = {}
    arms = {False: ["solid_contact.enabled=false"], True: ["solid_contact.approach_over_c0=0.0"],
            "case": []}  # off; the spring alone; the case's own (against approach only)
    for on, extra in arms.items():
        cfg = small(*base, *extra)
        dx = cfg["scene"]["dx_m"]
        _, sim = make_simulation(cfg)
        term = [t for t in sim.terms if isinstance(t, SolidContact)]
        assert bool(term) == bool(on)
        if on is True:
            assert term[0].limits(sim) == {} and sim.n_fluid == 0  # no melt yet: no spring, no limit
        seen = []
        for _ in range(30):
            run_steps(sim, steps=10)
            s = sim.state
            fl = s.phase == 0
            if bool(fl.any()):
                seen.append(float(torch.cdist(s.x[fl], s.x[~fl]).min()) / dx)
        assert len(seen) >= 10, "the scene must melt"
        closest[on] = min(seen)
        if on is True:
            lim = term[0].limits(sim)["solid_contact"]
            assert lim == pytest.approx(0.25 * dx / (0.25 * 2 * cfg["fluid"]["c0_m_s"] ** 2) ** 0.5)
            # at exactly r0 the repulsion is zero
            x = torch.zeros(2, 3, dtype=torch.float64)
            x[1, 0] = dx
            term[0].pi, term[0].pj = torch.tensor([0]), torch.tensor([1])
            sim.state.x, keep = x, sim.state.x
            assert float(term[0].acceleration(sim, None)[1].abs().max()) == 0.0
            sim.state.x = keep
    # the case's force acts only against approach: slow creep is resisted in proportion to its
    # speed, so melt comes a little closer than with the spring (measured 0.917 dx), far from 0.73 dx
    assert closest[False] < 0.85 and closest[True] >= 0.95 and closest["case"] >= 0.9, closest


def test_solid_contact_against_approach_only_stops_without_rebound():
    """[solid_contact] with approach_over_c0 > 0: the force acts only against a pair's
    closing speed w, scaled by min(1, w / u_s). A melt particle at rest inside the solid's
    spacing (one that has just melted there) is not pushed: the spring alone pushed such a
    particle at up to K/r0 and blew up the 0.35 mm perpendicular run (docs/RESOLUTION.md).
    A particle fired at a fixed solid particle is stopped short of it and stays (no
    rebound), where the spring alone sends it back at its approach speed."""
    from types import SimpleNamespace

    from torchsph.physics.terms.contact import SolidContact

    K, r0, u_s = 100.0, 1.0e-4, 0.2
    dom = SimpleNamespace(minimum_image=lambda d: d)

    def accel(term, gap, u):
        x = torch.tensor([[gap, 0.0, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
        v = torch.tensor([[u, 0.0, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
        term.pi, term.pj = torch.tensor([0]), torch.tensor([1])
        return float(term.acceleration(SimpleNamespace(state=SimpleNamespace(x=x), domain=dom), v)[1][0, 0])

    damped, spring = SolidContact(K, r0, u_s), SolidContact(K, r0)
    full = K / r0 * 0.25  # K (1 - r/r0)^2 / r0 at r = r0 / 2
    assert accel(spring, 0.5 * r0, 0.0) == pytest.approx(full)
    assert accel(damped, 0.5 * r0, 0.0) == 0.0  # at rest: nothing
    assert accel(damped, 0.5 * r0, 0.1) == 0.0  # moving apart: nothing
    assert accel(damped, 0.5 * r0, -2 * u_s) == pytest.approx(full)  # closing faster than u_s: the spring's
    assert accel(damped, 0.5 * r0, -0.5 * u_s) == pytest.approx(0.5 * full)

    def fire(term, w0, dt=2e-8):  # a head-on approach at w0, integrated until it leaves or stops
        gap, u, closest = r0, -w0, r0
        for _ in range(20000):
            u += dt * accel(term, gap, u)
            gap += dt * u
            closest = min(closest, gap)
            if gap >= r0 or abs(u) < 1e-4 * w0:
                break
        return closest, u

    w0 = 0.5 * (2 * K / 3) ** 0.5  # half the speed that crosses the spring's barrier K/3
    c_s, u_back = fire(spring, w0)
    c_d, u_end = fire(damped, w0)
    assert u_back == pytest.approx(w0, rel=1e-3)  # the spring: an elastic bounce
    assert 0 < c_d < r0 and -1e-4 * w0 < u_end <= 0  # approach only: stopped, no rebound
    assert c_d < c_s  # (softer than the spring: it stops the particle a little further in)
