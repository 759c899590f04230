"""A short-range repulsion that keeps melt out of the solid's lattice (a numerical boundary
safeguard, after Monaghan's boundary forces).

The wall condition (Adami 2012) stops melt that approaches solid only by compressing it: the
solid's kernel sum raises the melt's density and its pressure pushes back. At a coarse,
irregular (refrozen) solid beside a small pocket of melt, the pocket's own melt flowing apart
can lower a particle's density as fast as the solid raises it, and a surface force then moves
it through the solid unopposed (traced in docs/RESOLUTION.md, "The melt leak at 0.3 mm":
0.5 mm into the substrate at constant density, then a tensile runaway). This term adds, for
every melt particle i and solid or wall particle j closer than r0,

    a_i = K (1 - r/r0)^2 / r0 e_ij,    e_ij = (x_i - x_j) / r,   K = stiffness c0^2,

zero at and beyond r0 (a melt particle at a lattice spacing from a flat wall feels none: a
fluid at rest beside a wall is unchanged). Its potential barrier per unit mass is K/3 per
solid neighbour, so with the default stiffness 0.25 a particle needs ~c0/sqrt(6) of approach
speed to cross a single solid particle and more between several. The solid is kinematic
(rigid bodies move as prescribed), so it takes no reaction.

With ``approach_over_c0`` > 0 the force acts only against the pair's approach: it is
multiplied by min(1, w / u_s), w = -(u_i - u_j) . e_ij the closing speed, u_s =
approach_over_c0 c0. A melt particle that has just melted inside the solid's spacing (closer
than r0 to its refrozen neighbours) is at rest there, and the spring alone pushed it out at
up to K/r0 = 2.9e5 m/s^2 (the 0.35 mm ``perpendicular_350W`` run blew up so at 0.3156 s);
with the factor it is not pushed, and melt moving into the solid is stopped without the
spring's rebound (a dissipative contact, the damping half of Hunt & Crossley's). Below u_s
it is a damper of rate K q^2 / (r0 u_s), q = 1 - r/r0, and adds no time-step limit: a step
that turns a closing pair apart leaves it separating at most (K q^2 dt / (r0 u_s) - 1) w,
after which the force is zero (none where u_s >= K dt / r0; at the acoustic dt and the
default stiffness that is u_s >= ~0.09 c0, while 0.01 c0 was measured to pass). Time-step limit: the pair
spring's frequency sqrt(2K)/r0 at r -> 0, dt <= 0.25 r0 / sqrt(2K).

Pairs are found at each selection from the fluid's rows of the neighbour table, those closer
than r0 + skin at the reference positions (no pair can come within r0 before the next build
otherwise), and evaluated on that flat list every step."""
from __future__ import annotations

import math

import torch

from torchsph.core.schema import Key
from torchsph.core.state import Phase
from torchsph.physics.fluid import dot
from torchsph.physics.terms.base import Term, TermContext, register


@register
class SolidContact(Term):
    section = "solid_contact"
    doc = "short-range repulsion of melt from solid and walls within r0 (keeps melt out of the solid's lattice)"
    schema = {
        "stiffness": Key("float", default=0.25, gt=0, le=4.0, doc="K / c0^2 of a = K (1 - r/r0)^2 / r0"),
        "range_over_dx": Key("float", default=1.0, gt=0, le=1.5, doc="r0 / dx: the repulsion acts closer than this"),
        "approach_over_c0": Key("float", default=0.01, ge=0, le=1.0,
                                doc="> 0: the force only against approach, scaled by min(1, w / (this c0)), "
                                    "w the pair's closing speed; 0: a spring (pushes melt that melts "
                                    "inside the solid's spacing out: blew up a 0.35 mm deposition run)"),
    }
    needs = ("fluid",)
    reads = ("x", "phase")
    writes = ("acceleration",)
    limit_formulas = {"solid_contact": "0.25 r0 / sqrt(2 K): the contact spring's period"}

    def __init__(self, K: float, r0: float, u_s: float = 0.0):
        self.K, self.r0, self.u_s = K, r0, u_s
        self.pi = self.pj = None
        self.rows = None

    @classmethod
    def from_case(cls, cfg: dict, ctx: TermContext) -> "SolidContact":
        sc = cfg["solid_contact"]
        c0 = cfg["fluid"]["c0_m_s"]
        return cls(sc["stiffness"] * c0**2, sc["range_over_dx"] * ctx.dx, sc.get("approach_over_c0", 0.0) * c0)  # (absent in older runs: the spring they ran with)

    def select(self, sim) -> None:
        s, fm = sim.state, sim.fluid  # (None while there is no melt)
        if fm is None:
            self.pi = self.pj = torch.zeros(0, dtype=torch.long, device=s.x.device)
            return
        rows = fm.rows_f[: fm.n_momentum]  # (a decomposition's ghosts take their owners')
        nb, mk = sim.nl.table.gather(rows, within=True)
        x_ref = sim.nl.x_ref if sim.nl.x_ref is not None and sim.nl.x_ref.shape == s.x.shape else s.x
        cand = mk & (s.phase.index_select(0, nb.reshape(-1)).view_as(nb) != Phase.FLUID)
        d = sim.domain.minimum_image(x_ref.index_select(0, rows).unsqueeze(1)
                                     - x_ref.index_select(0, nb.reshape(-1)).view(*nb.shape, s.dim))
        cand = cand & (dot(d, d) < (self.r0 + sim.nl.skin) ** 2)
        at = torch.nonzero(cand.reshape(-1)).squeeze(1)
        k = nb.shape[1]
        self.pi = rows.index_select(0, torch.div(at, k, rounding_mode="floor"))
        self.pj = nb.reshape(-1).index_select(0, at)

    def acceleration(self, sim, v: torch.Tensor):
        x = sim.state.x
        d = sim.domain.minimum_image(x.index_select(0, self.pi) - x.index_select(0, self.pj))
        r = torch.sqrt(dot(d, d)).clamp_min(1e-12 * self.r0)
        q = (1.0 - r / self.r0).clamp_min(0.0)
        a = (self.K / self.r0) * q * q / r
        if self.u_s > 0:  # only against the pair's approach: a particle at rest is not pushed
            w = -dot(v.index_select(0, self.pi) - v.index_select(0, self.pj), d) / r  # closing speed
            a = a * (w / self.u_s).clamp(0.0, 1.0)
        return self.pi, d * a.unsqueeze(-1)

    def limits(self, sim) -> dict:
        if self.pi is None or not self.pi.numel():  # no melt near solid: no spring
            return {}
        return {"solid_contact": 0.25 * self.r0 / math.sqrt(2.0 * self.K)}

    def plan(self) -> str:
        return f"K = {self.K:.3g} m^2/s^2, r0 = {self.r0:.3g} m"
