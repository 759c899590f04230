"""The temperature gradient as a per-particle field, renormalised (Bonet & Lok 1999):

    grad T_i = L_i^-1 sum_j V_j (T_j - T_i) grad_i W_ij,   L_i = sum_j V_j (x_j - x_i) (x) grad_i W_ij,

exact for a linear temperature field wherever the neighbourhood spans every direction (L_i is
the identity there for a full lattice). Where L_i is nearly singular (a row with few neighbours,
or none on a side of a plane: det L_i < 1e-3, where a full lattice has 1 and a 3-D block's
corner 0.017) the uncorrected sum is kept. Wall particles take their mirrored Dirichlet temperature (as the conduction does), so the gradient beside a wall holds
the face temperature between the last solid and the first wall layer. Particles without a
table row (cold solid left out of the work) have gradient 0.

The field ``grad_T`` is made every step once the pairs are selected (the step's stages,
:mod:`torchsph.step.stages`); other terms read it (``reads = ("grad_T",)``), on their own rows or
their neighbours', and ``[run] fields = ["temperature_gradient"]`` writes it to the snapshots
(G = |grad T| at the fusion line is the thermal gradient of the solidification maps)."""
from __future__ import annotations

import torch

from torchsph.core.state import Array
from torchsph.physics.fluid import gather_nb, outer_sum, pair_geometry, pair_sum
from torchsph.physics.terms.base import Term, TermContext, register


@register
class TemperatureGradient(Term):
    section = "temperature_gradient"
    doc = "the renormalised temperature gradient grad_T (K/m) as a field other terms read"
    schema = {}
    needs = ("thermal",)
    reads = ("x", "m", "rho", "T")
    writes = ("grad_T",)
    ARRAYS = {"grad_T": Array("temperature gradient, renormalised SPH (exact for a linear field)", "K/m",
                              output="temperature_gradient", vector=True)}
    SINGULAR = 1e-3  # det L below this: the uncorrected gradient (a 3-D lattice corner: 0.017)

    def __init__(self, kernel, h: float):
        self.kernel, self.h = kernel, h
        self.grad_T = None

    @classmethod
    def from_case(cls, cfg: dict, ctx: TermContext) -> "TemperatureGradient":
        return cls(ctx.kernel, ctx.h)

    def evaluate(self, sim) -> None:
        s, th = sim.state, sim.thermal
        rows = sim.nl.table.rows
        nb, mask = sim.nl.table.gather(rows, within=True)
        T = th.wall_temperature(s, s.T)
        dx, r = pair_geometry(s.x, rows, nb, sim.domain, self.h)  # x_i - x_j
        dw = self.kernel.dwdr(r, self.h) / r * mask  # grad_i W_ij = dw dx
        wV = dw * gather_nb(s.m / s.rho, nb)
        g = pair_sum(wV * (gather_nb(T, nb) - T.index_select(0, rows).unsqueeze(1)), dx)
        L = -outer_sum(wV.unsqueeze(-1) * dx, dx)  # sum_j V_j (x_j - x_i) (x) grad_i W_ij
        ok = torch.linalg.det(L) > self.SINGULAR
        eye = torch.eye(s.dim, dtype=L.dtype, device=L.device)
        corr = torch.linalg.solve(torch.where(ok.view(-1, 1, 1), L, eye), g.unsqueeze(-1)).squeeze(-1)
        out = torch.zeros_like(s.x)
        self.grad_T = out.index_copy_(0, rows, torch.where(ok.unsqueeze(-1), corr, g))

    def plan(self) -> str:
        return "renormalised, on every working row"
