"""The term protocol (torchsph/terms): a term a case names is built and evaluated at its
hooks, and its per-particle arrays travel with the particles."""
import pytest
import torch

from conftest import CASES
from torchsph import checkpoint as ckpt
from torchsph import particles
from torchsph.config import load_case
from torchsph.runner import make_simulation, run_steps
from torchsph.terms import TERMS, Term, register


def test_a_terms_per_particle_arrays_travel_with_the_particles(tmp_path, monkeypatch):
    """The array registry carries a term's own per-particle arrays: in particle_arrays,
    through a checkpoint and its restore, and through particle removal (a term made here,
    registered for this test only, that counts each particle's heat-evaluations)."""
    class Tally(Term):
        section = "tally"
        writes = ("heat",)

        @classmethod
        def from_case(cls, cfg, ctx):
            return cls()

        def select(self, sim):
            if getattr(self, "count", None) is None or self.count.shape[0] != sim.state.n:
                self.count = torch.zeros(sim.state.n, dtype=torch.long)

        def heat(self, sim, t, rows):
            self.count.index_add_(0, rows, torch.ones_like(rows))
            return torch.zeros(rows.numel(), dtype=sim.state.dtype)

        def arrays(self):
            return {"count": self.count}

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
        with pytest.raises(TypeError, match="a term needs a section and writes only"):
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
